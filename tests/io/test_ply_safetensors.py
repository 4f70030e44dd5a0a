"""graphdeco PLY and safetensors I/O: exact round trips, foreign layouts, clear errors, atomic writes."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from fmgs.errors import ValidationError
from fmgs.gaussians import GaussianSet
from fmgs.io.ply import ply_property_names, read_ply, write_ply
from fmgs.io.tensors import load_gaussians, save_gaussians


def _set(n=50, degree=3, seed=0) -> GaussianSet:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return GaussianSet(
        torch.randn(n, 3, generator=g),
        torch.randn(n, 4, generator=g),
        torch.randn(n, 3, generator=g),
        torch.randn(n, generator=g),
        torch.randn(n, k, 3, generator=g),
    )


def _same(a: GaussianSet, b: GaussianSet) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a.tensors().values(), b.tensors().values(), strict=True))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_ply_round_trip_is_bit_exact(tmp_path, degree):
    g = _set(degree=degree)
    write_ply(g, tmp_path / "a.ply")
    h = read_ply(tmp_path / "a.ply")
    assert _same(g, h)
    write_ply(h, tmp_path / "b.ply")
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()


def _graphdeco_style_file(path, g: GaussianSet, names=None, byte_order="<", text=False, extra=()):
    """Write the way graphdeco's save_ply does (one float32 structured vertex element)."""
    n, k = g.num, g.sh.shape[1]
    cols = {
        "x": g.means[:, 0],
        "y": g.means[:, 1],
        "z": g.means[:, 2],
        "nx": torch.zeros(n),
        "ny": torch.zeros(n),
        "nz": torch.zeros(n),
        "opacity": g.opacity_logits,
    }
    for c in range(3):
        cols[f"f_dc_{c}"] = g.sh[:, 0, c]
        for j in range(k - 1):
            cols[f"f_rest_{c * (k - 1) + j}"] = g.sh[:, 1 + j, c]  # channel-major, as graphdeco flattens
    for i in range(3):
        cols[f"scale_{i}"] = g.log_scales[:, i]
    for i in range(4):
        cols[f"rot_{i}"] = g.quats[:, i]
    names = names or ply_property_names(g.sh_degree)
    dt = [(nm, "f4") for nm in names] + [(nm, t) for nm, t, _ in extra]
    rec = np.empty(n, dtype=dt)
    for nm in names:
        rec[nm] = cols[nm].numpy()
    for nm, _, vals in extra:
        rec[nm] = vals
    PlyData([PlyElement.describe(rec, "vertex")], text=text, byte_order=byte_order).write(str(path))


def test_graphdeco_file_loads_and_rewrites_byte_identical(tmp_path):
    g = _set()
    _graphdeco_style_file(tmp_path / "point_cloud.ply", g)
    h = read_ply(tmp_path / "point_cloud.ply")
    assert _same(g, h)
    write_ply(h, tmp_path / "ours.ply")
    assert (tmp_path / "ours.ply").read_bytes() == (tmp_path / "point_cloud.ply").read_bytes()


def test_f_rest_is_channel_major(tmp_path):
    n, k = 2, 4
    sh = torch.zeros(n, k, 3)
    for j in range(k):
        for c in range(3):
            sh[:, j, c] = 10 * j + c
    g = GaussianSet(
        torch.zeros(n, 3), torch.tensor([[1.0, 0, 0, 0]] * n), torch.zeros(n, 3), torch.zeros(n), sh
    )
    write_ply(g, tmp_path / "a.ply")
    v = PlyData.read(str(tmp_path / "a.ply"))["vertex"]
    # f_rest_{c*(K-1)+j} holds coefficient j+1 of channel c
    assert (
        v["f_rest_0"][0] == 10
        and v["f_rest_2"][0] == 30
        and v["f_rest_3"][0] == 11
        and v["f_rest_8"][0] == 32
    )


@pytest.mark.parametrize(
    "variant",
    ["no_normals", "shuffled", "ascii", "big_endian", "extra_rgb", "degree0"],
)
def test_foreign_layouts_load(tmp_path, variant):
    """Exporters differ in property order, normals, extra colour columns, encoding and endianness."""
    g = _set(n=20, degree=0 if variant == "degree0" else 3)
    names = ply_property_names(g.sh_degree)
    kw = {}
    if variant == "no_normals":
        names = [n for n in names if n not in ("nx", "ny", "nz")]
    elif variant == "shuffled":
        names = list(reversed(names))
    elif variant == "ascii":
        kw["text"] = True
    elif variant == "big_endian":
        kw["byte_order"] = ">"
    elif variant == "extra_rgb":
        kw["extra"] = [(c, "u1", np.arange(20, dtype=np.uint8)) for c in ("red", "green", "blue")]
    _graphdeco_style_file(tmp_path / "f.ply", g, names=names, **kw)
    h = read_ply(tmp_path / "f.ply")
    if variant == "ascii":  # text keeps ~9 significant digits
        for a, b in zip(g.tensors().values(), h.tensors().values(), strict=True):
            assert torch.allclose(a, b, rtol=1e-6, atol=1e-7)
    else:
        assert _same(g, h)


def test_ply_errors_name_the_problem(tmp_path):
    with pytest.raises(ValidationError, match="no such file"):
        read_ply(tmp_path / "missing.ply")
    (tmp_path / "junk.ply").write_bytes(b"not a ply at all\n" * 10)
    with pytest.raises(ValidationError, match="not a readable PLY"):
        read_ply(tmp_path / "junk.ply")
    g = _set(n=10)
    names = [n for n in ply_property_names(3) if n != "opacity"]
    _graphdeco_style_file(tmp_path / "noop.ply", g, names=names)
    with pytest.raises(ValidationError, match="lacks property 'opacity'"):
        read_ply(tmp_path / "noop.ply")
    names = [n for n in ply_property_names(3) if n != "f_rest_44"]
    _graphdeco_style_file(tmp_path / "rest.ply", g, names=names)
    with pytest.raises(ValidationError, match="f_rest"):
        read_ply(tmp_path / "rest.ply")
    bad = _set(n=10)
    bad.log_scales[6, 1] = float("nan")
    _graphdeco_style_file(tmp_path / "nan.ply", bad)
    with pytest.raises(ValidationError, match=r"nan.ply: log_scales at index 6: contains NaN"):
        read_ply(tmp_path / "nan.ply")


def test_truncated_ply_is_rejected(tmp_path):
    write_ply(_set(n=100), tmp_path / "a.ply")
    data = (tmp_path / "a.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValidationError, match=r"t\.ply"):
        read_ply(tmp_path / "t.ply")


def test_failed_write_leaves_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "scene.ply"
    write_ply(_set(seed=1), path)
    before = path.read_bytes()

    def boom(self, stream):
        with open(stream, "wb") as f:
            f.write(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(PlyData, "write", boom)
    with pytest.raises(OSError, match="disk full"):
        write_ply(_set(seed=2), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["scene.ply"]  # no temp file left behind


def test_safetensors_round_trip_and_errors(tmp_path):
    g = _set(degree=2)
    save_gaussians(g, tmp_path / "g.safetensors")
    assert _same(g, load_gaussians(tmp_path / "g.safetensors"))
    from safetensors.torch import save_file

    save_file({"means": torch.zeros(2, 3)}, str(tmp_path / "other.safetensors"))
    with pytest.raises(ValidationError, match=r"not an fmgs\.gaussians file"):
        load_gaussians(tmp_path / "other.safetensors")
    save_file(
        {"means": torch.zeros(2, 3)},
        str(tmp_path / "partial.safetensors"),
        metadata={"format": "fmgs.gaussians", "version": "1"},
    )
    with pytest.raises(ValidationError, match="missing tensors"):
        load_gaussians(tmp_path / "partial.safetensors")
    (tmp_path / "junk.safetensors").write_bytes(b"\x00" * 20)
    with pytest.raises(ValidationError, match="cannot read"):
        load_gaussians(tmp_path / "junk.safetensors")


def test_an_unsupported_sh_degree_names_the_file(tmp_path):
    """72 f_rest properties (degree 4) or 12 (no degree): the error named only 'sh', not the file."""
    for rest in (72, 12):
        names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", *(f"f_rest_{i}" for i in range(rest))]
        names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
        rec = np.zeros(3, dtype=[(n, "<f4") for n in names])
        rec["rot_0"] = 1.0
        PlyData([PlyElement.describe(rec, "vertex")]).write(str(tmp_path / "d.ply"))
        with pytest.raises(
            ValidationError, match=rf"d\.ply: {rest} f_rest_\* properties: SH coefficient count"
        ):
            read_ply(tmp_path / "d.ply")
