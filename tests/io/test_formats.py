"""Other tools' 3DGS files: antimatter15 .splat, SuperSplat compressed PLY, graphdeco PLY with extra columns.

Files are written here by test-side encoders that follow each format's description (not our decoders
run backwards); decoded values must land within the format's quantisation bounds.
"""

from __future__ import annotations

import json
import logging
import math

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from fmgs.cli import main
from fmgs.errors import ValidationError
from fmgs.gaussians import SH_C0, GaussianSet
from fmgs.io.ply import ply_property_names, read_ply, write_ply


def _set(n=40, degree=0, seed=0, colour_range=1.0) -> GaussianSet:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    sh = torch.randn(n, k, 3, generator=g).clamp(-3.5, 3.5)
    # DC inside what an 8-bit colour holds, so the writer's clipping does not enter the comparison.
    sh[:, 0] = (torch.rand(n, 3, generator=g) - 0.5) * colour_range / SH_C0
    return GaussianSet(
        torch.randn(n, 3, generator=g) * 3,
        torch.randn(n, 4, generator=g),
        torch.randn(n, 3, generator=g) - 3,
        torch.randn(n, generator=g) * 2,
        sh,
    )


def _aligned(q: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Quaternions q [N,4] with the sign that points them the way of ref [N,4] (q and -q are one rotation)."""
    return q * torch.where((q * ref).sum(1, keepdim=True) < 0, -1.0, 1.0)


# --- .splat ------------------------------------------------------------------------------------------


def _encode_splat(g: GaussianSet, rounding=np.round) -> bytes:
    """32 bytes per Gaussian as antimatter15's writers produce them (``rounding``: theirs differ)."""
    n = g.num
    rgba = np.concatenate(
        [0.5 + SH_C0 * g.sh[:, 0].numpy(), torch.sigmoid(g.opacity_logits).numpy()[:, None]], axis=1
    )
    q = (g.quats / g.quats.norm(dim=1, keepdim=True)).numpy()
    out = bytearray()
    for i in range(n):
        out += g.means[i].numpy().astype("<f4").tobytes()
        out += g.scales[i].numpy().astype("<f4").tobytes()
        out += np.clip(rounding(rgba[i] * 255), 0, 255).astype(np.uint8).tobytes()
        out += np.clip(rounding(q[i] * 128 + 128), 0, 255).astype(np.uint8).tobytes()
    return bytes(out)


@pytest.mark.parametrize("rounding", [np.round, np.trunc], ids=["web_viewer", "convert_py"])
def test_splat_decodes_within_one_step(tmp_path, rounding):
    g = _set(n=64)
    (tmp_path / "s.splat").write_bytes(_encode_splat(g, rounding))
    h = read_ply(tmp_path / "s.splat")
    assert h.num == 64 and h.sh_degree == 0 and h.dtype == torch.float32
    assert torch.equal(h.means, g.means)
    assert torch.allclose(h.scales, g.scales, rtol=1e-6)
    # One storage step: 1/255 of colour and alpha, 1/128 of a unit quaternion's component.
    rgb = 0.5 + SH_C0 * h.sh[:, 0]
    assert (rgb - (0.5 + SH_C0 * g.sh[:, 0])).abs().max() <= 1 / 255 + 1e-6
    assert (h.opacities - g.opacities).abs().max() <= 1 / 255 + 1e-6
    q = g.quats / g.quats.norm(dim=1, keepdim=True)
    assert (_aligned(h.quats, q) - q).abs().max() <= 1 / 128 + 1e-6


def test_splat_literal_record(tmp_path):
    """One record built byte by byte from the format's description."""
    rec = np.array([1.5, -2.0, 3.25], "<f4").tobytes() + np.array([0.5, 1.0, 2.0], "<f4").tobytes()
    rec += bytes([255, 0, 128, 255]) + bytes([255, 128, 128, 1])
    (tmp_path / "one.splat").write_bytes(rec)
    h = read_ply(tmp_path / "one.splat")
    assert h.means.tolist() == [[1.5, -2.0, 3.25]]
    assert torch.allclose(h.log_scales, torch.log(torch.tensor([[0.5, 1.0, 2.0]])))
    assert torch.equal(h.quats, torch.tensor([[127 / 128, 0.0, 0.0, -127 / 128]]))
    f_dc = (torch.tensor([255, 0, 128]) / 255 - 0.5) / SH_C0
    assert torch.allclose(h.sh[0, 0], f_dc, atol=1e-6)
    # alpha 255 cannot be a finite logit: it is read inside its bin, so rounding gives 255 back.
    assert torch.isfinite(h.opacity_logits).all() and round(float(h.opacities[0]) * 255) == 255


def test_malformed_splat_names_file_and_format(tmp_path):
    good = _encode_splat(_set(n=3))
    cases = {
        "trunc.splat": (good[:-5], r"trunc\.splat: size 91 bytes is not a positive multiple of 32"),
        "empty.splat": (b"", r"empty\.splat: size 0 bytes"),
        "zeroq.splat": (
            good[:64] + good[64:92] + bytes([128] * 4),
            r"zeroq\.splat: quats at index 2: zero quaternion.*\(read as antimatter15 \.splat\)",
        ),
        "negscale.splat": (
            good[:44] + np.float32(-1).tobytes() + good[48:],
            r"negscale\.splat at index 1: scales must be finite and positive \(read as antimatter15",
        ),
        "nan.splat": (
            np.float32(np.nan).tobytes() + good[4:],
            r"nan\.splat: means at index 0: contains NaN or Inf \(read as antimatter15 \.splat\)",
        ),
    }
    for name, (data, match) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(ValidationError, match=match):
            read_ply(tmp_path / name)


def test_cli_info_reads_splat(tmp_path, capsys):
    (tmp_path / "s.splat").write_bytes(_encode_splat(_set(n=10)))
    assert main(["info", str(tmp_path / "s.splat")]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["gaussians"] == 10 and info["sh_degree"] == 0


# --- SuperSplat compressed PLY -----------------------------------------------------------------------

CHUNK = 256


def _pack_unorm(t: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    return np.clip(np.floor(t * top + 0.5), 0, top).astype(np.uint32)


def _normalise(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return np.clip((x - lo) / (hi - lo), 0, 1) if hi - lo >= 1e-5 else np.zeros_like(x)


def _pack3(t: np.ndarray, bits=(11, 10, 11)) -> np.ndarray:
    """[N,3] fractions -> uint32 words, first field in the top bits."""
    a, b, c = (_pack_unorm(t[:, i], bits[i]) for i in range(3))
    return (a << np.uint32(bits[1] + bits[2])) | (b << np.uint32(bits[2])) | c


def _pack_rot(q: np.ndarray) -> np.ndarray:
    """Smallest three: 2 bits for the largest |component|, then the rest in [-1/sqrt2, 1/sqrt2], 10 bits."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    out = np.empty(len(q), np.uint32)
    for i, row in enumerate(q):
        big = int(np.argmax(np.abs(row)))
        row = -row if row[big] < 0 else row
        word = big
        for j in range(4):
            if j != big:
                word = (word << 10) | int(_pack_unorm(row[j] * math.sqrt(0.5) + 0.5, 10))
        out[i] = word
    return out


def _encode_compressed(g: GaussianSet, chunk_colours=True, drop=()) -> list[PlyElement]:
    """The elements splat-transform writes (chunk, vertex, sh), chunk by chunk in file order."""
    n, k = g.num, g.sh.shape[1]
    means, ls = g.means.numpy().astype(np.float64), g.log_scales.numpy().astype(np.float64)
    rgb = 0.5 + SH_C0 * g.sh[:, 0].numpy().astype(np.float64)
    alpha = torch.sigmoid(g.opacity_logits.double()).numpy()
    chunks, packed = [], np.zeros((n, 4), np.uint32)
    for c0 in range(0, n, CHUNK):
        s = slice(c0, min(n, c0 + CHUNK))
        row = []
        for vals, clamp in ((means[s], None), (ls[s], 20.0), (rgb[s], None)):
            lo, hi = vals.min(0), vals.max(0)
            if clamp:
                lo, hi = np.clip(lo, -clamp, clamp), np.clip(hi, -clamp, clamp)
            row.append((lo, hi, np.stack([_normalise(vals[:, i], lo[i], hi[i]) for i in range(3)], 1)))
        (plo, phi, pt), (slo, shi, st), (clo, chi, ct) = row
        if not chunk_colours:
            ct = np.clip(rgb[s], 0, 1)
        chunks.append([*plo, *phi, *slo, *shi] + ([*clo, *chi] if chunk_colours else []))
        packed[s, 0] = _pack3(pt)
        packed[s, 1] = _pack_rot(g.quats[s].numpy().astype(np.float64))
        packed[s, 2] = _pack3(st)
        c8 = [_pack_unorm(ct[:, i], 8) for i in range(3)] + [_pack_unorm(alpha[s], 8)]
        packed[s, 3] = (c8[0] << np.uint32(24)) | (c8[1] << np.uint32(16)) | (c8[2] << np.uint32(8)) | c8[3]
    cnames = [f"{m}_{a}" for m in ("min", "max") for a in "xyz"]
    cnames += [f"{m}_scale_{a}" for m in ("min", "max") for a in "xyz"]
    cnames += [f"{m}_{a}" for m in ("min", "max") for a in "rgb"] if chunk_colours else []
    crec = np.array([tuple(r) for r in chunks], dtype=[(c, "<f4") for c in cnames])
    vnames = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]
    vrec = np.empty(n, dtype=[(v, "<u4") for v in vnames])
    for i, v in enumerate(vnames):
        vrec[v] = packed[:, i]
    elements = {"chunk": PlyElement.describe(crec, "chunk"), "vertex": PlyElement.describe(vrec, "vertex")}
    if k > 1:
        rest = g.sh[:, 1:].numpy().transpose(0, 2, 1).reshape(n, -1)  # channel-major f_rest order
        b = np.clip(np.trunc((rest / 8 + 0.5) * 256), 0, 255).astype(np.uint8)
        srec = np.empty(n, dtype=[(f"f_rest_{i}", "u1") for i in range(rest.shape[1])])
        for i in range(rest.shape[1]):
            srec[f"f_rest_{i}"] = b[:, i]
        elements["sh"] = PlyElement.describe(srec, "sh")
    return [e for name, e in elements.items() if name not in drop]


def _write(path, elements) -> None:
    PlyData(elements, byte_order="<").write(str(path))


def _chunk_range(x: torch.Tensor) -> torch.Tensor:
    """[N,C] per-Gaussian range (max - min) of x [N,C] over its 256-chunk."""
    out = torch.empty_like(x)
    for c0 in range(0, len(x), CHUNK):
        s = slice(c0, c0 + CHUNK)
        out[s] = x[s].max(0).values - x[s].min(0).values
    return out


@pytest.mark.parametrize(("degree", "chunk_colours"), [(0, True), (0, False), (1, True), (3, True)])
def test_compressed_ply_decodes_within_quantisation(tmp_path, degree, chunk_colours):
    g = _set(n=600, degree=degree, colour_range=0.9)  # 3 chunks, the last one partial
    _write(tmp_path / "c.compressed.ply", _encode_compressed(g, chunk_colours))
    h = read_ply(tmp_path / "c.compressed.ply")
    assert h.num == 600 and h.sh_degree == degree
    half = torch.tensor([0.5 / 2047, 0.5 / 1023, 0.5 / 2047])  # 11/10/11 bits
    eps = 1e-5
    assert ((h.means - g.means).abs() <= _chunk_range(g.means) * half + eps).all()
    assert ((h.log_scales - g.log_scales).abs() <= _chunk_range(g.log_scales) * half + eps).all()
    rgb, rgb_h = 0.5 + SH_C0 * g.sh[:, 0], 0.5 + SH_C0 * h.sh[:, 0]
    span = _chunk_range(rgb) if chunk_colours else torch.ones_like(rgb)
    assert ((rgb_h - rgb).abs() <= span * 0.5 / 255 + eps).all()
    assert ((h.opacities - g.opacities).abs() <= 0.5 / 255 + eps).all()
    q = g.quats / g.quats.norm(dim=1, keepdim=True)
    qh = _aligned(h.quats, q)
    assert (h.quats.norm(dim=1) - 1).abs().max() < 1e-5
    big = q.abs().argmax(dim=1, keepdim=True)
    err = (qh - q).abs()
    assert (err.scatter(1, big, 0) <= math.sqrt(2) * 0.5 / 1023 + eps).all()  # the three stored
    assert (err.gather(1, big) <= 3e-3).all()  # rebuilt from the norm: carries their error
    if degree:
        assert ((h.sh[:, 1:] - g.sh[:, 1:]).abs() <= 0.5 * 8 / 256 + eps).all()  # half a bin, |f| < 4


def test_compressed_ply_bit_layout(tmp_path):
    """Words built by hand from the layout: which bits are x, y, z, r, g, b, alpha and the largest axis."""
    cnames = [f"{m}_{a}" for m in ("min", "max") for a in "xyz"]
    cnames += [f"{m}_scale_{a}" for m in ("min", "max") for a in "xyz"]
    crec = np.array([(0, 0, 0, 1, 1, 1, -1, -1, -1, 1, 1, 1)], dtype=[(c, "<f4") for c in cnames])
    words = [
        # packed_position, packed_rotation, packed_scale, packed_color
        (0x7FF << 21, (2 << 30) | (512 << 20) | (512 << 10) | 512, 0x3FF << 11, 0xFF000000),
        (0x3FF << 11, (0 << 30) | (1023 << 20) | (0 << 10) | 0, 0x7FF, 0x00FF00FF),
    ]
    vnames = ("packed_position", "packed_rotation", "packed_scale", "packed_color")
    vrec = np.array(words, dtype=[(v, "<u4") for v in vnames])
    sh_bytes = [0, 64, 255, 1, 2, 3, 4, 5, 6]  # degree 1: f_rest_0..8, red's three first
    srec = np.array([tuple(sh_bytes)] * 2, dtype=[(f"f_rest_{i}", "u1") for i in range(9)])
    elements = [PlyElement.describe(r, e) for r, e in ((crec, "chunk"), (vrec, "vertex"), (srec, "sh"))]
    _write(tmp_path / "hand.ply", elements)
    h = read_ply(tmp_path / "hand.ply")
    # Byte s is the middle of [s/256, (s+1)/256) over [-4, 4]; 0 and 255 are the ends.
    want = [-4.0, (64.5 / 256 - 0.5) * 8, 4.0] + [(b + 0.5) / 32 - 4 for b in sh_bytes[3:]]
    assert h.sh[0, 1:].T.flatten().tolist() == pytest.approx(want, abs=1e-6)
    assert h.means.tolist() == [[1, 0, 0], [0, 1, 0]]
    assert h.log_scales.tolist() == [[-1, 1, -1], [-1, -1, 1]]
    rgb = 0.5 + SH_C0 * h.sh[:, 0]
    assert torch.allclose(rgb, torch.tensor([[1.0, 0, 0], [0, 1, 0]]), atol=1e-6)
    assert h.opacities[0] < 0.01 and h.opacities[1] > 0.99
    small = (512 / 1023 - 0.5) * math.sqrt(2)
    assert torch.allclose(h.quats[0], torch.tensor([small, small, math.sqrt(1 - 3 * small**2), small]))
    a = (1 - 0.5) * math.sqrt(2)  # 1023 -> +1/sqrt2, 0 -> -1/sqrt2, largest rebuilt as 0
    assert torch.allclose(h.quats[1], torch.tensor([0.0, a, -a, -a]), atol=1e-6)


def test_malformed_compressed_ply_names_file_and_format(tmp_path):
    g = _set(n=300, degree=1)
    fmt = r"\(read as SuperSplat compressed PLY\)"
    _write(tmp_path / "nochunk.ply", _encode_compressed(g, drop=("chunk",)))
    with pytest.raises(ValidationError, match=rf"nochunk\.ply: no 'chunk' element {fmt}"):
        read_ply(tmp_path / "nochunk.ply")
    els = _encode_compressed(g)
    els[0] = PlyElement.describe(els[0].data[:1], "chunk")
    _write(tmp_path / "fewchunks.ply", els)
    with pytest.raises(ValidationError, match=rf"fewchunks\.ply: 1 chunks for 300 Gaussians.*{fmt}"):
        read_ply(tmp_path / "fewchunks.ply")
    els = _encode_compressed(g)
    two = np.empty(300, dtype=[("f_rest_0", "u1"), ("f_rest_1", "u1")])
    two["f_rest_0"], two["f_rest_1"] = els[2].data["f_rest_0"], els[2].data["f_rest_1"]
    els[2] = PlyElement.describe(two, "sh")
    _write(tmp_path / "sh.ply", els)
    with pytest.raises(ValidationError, match=rf"sh\.ply: sh element has 2 properties.*{fmt}"):
        read_ply(tmp_path / "sh.ply")
    els = _encode_compressed(g)
    els[1] = PlyElement.describe(els[1].data.astype([(n, "<f4") for n in els[1].data.dtype.names]), "vertex")
    _write(tmp_path / "float.ply", els)
    with pytest.raises(ValidationError, match=rf"float\.ply: packed_position must be uint32.*{fmt}"):
        read_ply(tmp_path / "float.ply")


# --- graphdeco PLY with extra columns ----------------------------------------------------------------


def _graphdeco(path, g: GaussianSet, extra: dict[str, np.ndarray]) -> None:
    write_ply(g, path)
    v = PlyData.read(str(path))["vertex"].data
    names = ply_property_names(g.sh_degree)
    rec = np.empty(len(v), dtype=[(n, "<f4") for n in names] + [(n, "<f4") for n in extra])
    for n in names:
        rec[n] = v[n]
    for n, vals in extra.items():
        rec[n] = vals
    PlyData([PlyElement.describe(rec, "vertex")], byte_order="<").write(str(path))


def test_unknown_extras_warn_once_naming_them(tmp_path, caplog):
    g = _set(n=8, degree=1)
    _graphdeco(tmp_path / "x.ply", g, {"semantic_0": np.zeros(8), "depth_conf": np.ones(8)})
    with caplog.at_level(logging.WARNING, logger="fmgs.io.ply"):
        h = read_ply(tmp_path / "x.ply")
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert "x.ply" in warnings[0] and "semantic_0" in warnings[0] and "depth_conf" in warnings[0]
    assert all(torch.equal(a, b) for a, b in zip(g.tensors().values(), h.tensors().values(), strict=True))
    caplog.clear()
    write_ply(g, tmp_path / "plain.ply")  # normals only: nothing to say
    with caplog.at_level(logging.WARNING, logger="fmgs.io.ply"):
        read_ply(tmp_path / "plain.ply")
    assert not caplog.records


def test_mip_splatting_filter_3d_is_folded_in(tmp_path, caplog):
    g = _set(n=6, degree=0)
    filt = np.array([0.0, 0.01, 0.1, 1.0, 5.0, 0.0], np.float32)
    _graphdeco(tmp_path / "mip.ply", g, {"filter_3D": filt})
    with caplog.at_level(logging.WARNING, logger="fmgs.io.ply"):
        h = read_ply(tmp_path / "mip.ply")
    assert not caplog.records  # a known property, applied
    # Mip-Splatting's get_scaling_with_3D_filter / get_opacity_with_3D_filter, in float64.
    s2 = g.scales.double() ** 2
    f2 = torch.from_numpy(filt).double()[:, None] ** 2
    scales = (s2 + f2).sqrt()
    op = g.opacities.double() * (s2.prod(1) / (s2 + f2).prod(1)).sqrt()
    assert torch.allclose(h.scales.double(), scales, rtol=1e-5)
    assert torch.allclose(h.opacities.double(), op, rtol=1e-4, atol=1e-7)
    assert (h.opacities[1:5] < g.opacities[1:5]).all()
    for i in (0, 5):  # filter 0: the row's bits as stored
        assert torch.equal(h.log_scales[i], g.log_scales[i])
        assert torch.equal(h.opacity_logits[i], g.opacity_logits[i])
    assert torch.equal(h.means, g.means) and torch.equal(h.quats, g.quats) and torch.equal(h.sh, g.sh)


def test_filter_3d_edge_rows_stay_finite_and_exact(tmp_path):
    """A filter too small to move a float32 scale leaves the row's bits; a saturated opacity stays finite."""
    g = _set(n=3, degree=0)
    g.opacity_logits[:] = torch.tensor([60.0, 60.0, -60.0])
    _graphdeco(tmp_path / "edge.ply", g, {"filter_3D": np.array([1e-12, 1.0, 1.0], np.float32)})
    h = read_ply(tmp_path / "edge.ply")
    assert torch.equal(h.log_scales[0], g.log_scales[0])
    assert torch.equal(h.opacity_logits[0], g.opacity_logits[0])
    assert torch.isfinite(h.opacity_logits).all() and (h.log_scales[1:] > g.log_scales[1:]).all()
