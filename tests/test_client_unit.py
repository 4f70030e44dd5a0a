"""The thin client without the real server: codec, chunk reassembly, images, PLY, cameras, Open3D helpers,
and the client and CLI end to end against a small in-process fake of the service."""

from __future__ import annotations

import importlib.util
import io
import os
import struct
import subprocess
import sys
import zlib
from concurrent import futures
from pathlib import Path

import grpc
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from fmgs_client import cli
from fmgs_client.client import (
    ChunkError,
    FmgsClient,
    FmgsError,
    assemble_render,
    assemble_render_stream,
    assemble_segment,
    assemble_text_answers,
    decode_health_response,
    encode_health_request,
)
from fmgs_client.ply import read_ply, write_ply
from fmgs_client.types import Box, CameraSpec, Instance, TextAnswer
from fmgs_wire.images import colorize, decode_png, encode_png, write_png
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc
from fmgs_wire.tensors import TensorError, from_tensor, row_chunks, to_tensor

ROOT = Path(__file__).resolve().parents[1]
HAS_HEALTH = importlib.util.find_spec("grpc_health") is not None  # a server dependency, not the client's
DTYPES = ["float32", "float16", "float64", "int32", "int64", "uint8"]

# ---------------------------------------------------------------- tensor codec


@st.composite
def arrays(draw):
    dt = np.dtype(draw(st.sampled_from(DTYPES)))
    if draw(st.booleans()) and dt.itemsize > 1:
        dt = dt.newbyteorder(">")  # big-endian input must be encoded little-endian on the wire
    shape = draw(hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=5))
    return draw(hnp.arrays(dt, shape, elements={"allow_nan": False} if dt.kind == "f" else None))


@given(arrays())
def test_tensor_round_trip(a):
    t = to_tensor(a)
    assert list(t.shape) == list(a.shape)
    b = from_tensor(t)
    assert b.shape == a.shape and b.dtype == a.dtype.newbyteorder("=") and b.dtype.isnative
    np.testing.assert_array_equal(b, a)
    # Wire bytes are little-endian whatever the input's byte order.
    assert t.data == np.ascontiguousarray(a, a.dtype.newbyteorder("<")).tobytes()
    # A non-contiguous view encodes its values, not its memory.
    if a.ndim >= 1 and a.shape[0] > 1:
        np.testing.assert_array_equal(from_tensor(to_tensor(a[::2])), a[::2])


@pytest.mark.parametrize(
    "tensor, match",
    [
        (pb.Tensor(dtype=pb.DTYPE_FLOAT32, shape=[3], data=b"\0" * 8), "needs 12 bytes, got 8"),
        (pb.Tensor(dtype=pb.DTYPE_INT64, shape=[2, 0], data=b"\0"), "needs 0 bytes"),
        (pb.Tensor(dtype=pb.DTYPE_UNSPECIFIED, shape=[1], data=b"\0" * 4), "dtype"),
        (pb.Tensor(dtype=99, shape=[1], data=b"\0" * 4), "dtype"),
        (pb.Tensor(dtype=pb.DTYPE_UINT8, shape=[-1], data=b""), "bad shape"),
        (pb.Tensor(dtype=pb.DTYPE_UINT8, shape=[1] * 9, data=b"\0"), "bad shape"),
    ],
)
def test_malformed_tensor_names_the_field(tensor, match):
    with pytest.raises(TensorError, match=match) as e:
        from_tensor(tensor, "answer.relevancy")
    assert e.value.field == "answer.relevancy" and str(e.value).startswith("answer.relevancy:")


def test_unsupported_dtype_is_refused():
    with pytest.raises(TensorError, match="unsupported dtype"):
        to_tensor(np.zeros(3, np.uint16))


# ---------------------------------------------------------------- chunk builders (what a server sends)


def text_chunks(i, text, cols, instances=(), rows_per_chunk=2, elapsed=1.5):
    """Chunks of one text's answer: ``cols`` maps chunk field names to [K,...] arrays."""
    k = len(cols["index"])
    out = []
    for s, e in row_chunks(k, 1, rows_per_chunk):
        c = pb.TextQueryChunk(text_index=i, start=s)
        if s == 0:
            c.text, c.total, c.elapsed_ms = text, k, elapsed
            c.instances.extend(instances)
        for n, a in cols.items():
            getattr(c, n).CopyFrom(to_tensor(a[s:e]))
        out.append(c)
    return out


def interleave(*lists):
    out, lists = [], [list(x) for x in lists]
    while any(lists):
        for x in lists:
            if x:
                out.append(x.pop(0))
    return out


def pb_box(center, extent, rot=None):
    return pb.Box(center=center, extent=extent, rotation=[] if rot is None else list(np.ravel(rot)))


def answer_cols(rng, k, with_fields=True):
    cols = {
        "index": rng.permutation(1000)[:k].astype(np.int64),
        "relevancy": np.sort(rng.random(k).astype(np.float32))[::-1].copy(),
    }
    if with_fields:
        cols["mean"] = rng.normal(size=(k, 3)).astype(np.float32)
        cols["similarity"] = rng.random(k).astype(np.float32)
        cols["instance"] = rng.integers(-1, 2, k).astype(np.int32)
    return cols


def test_text_answers_interleaved():
    rng = np.random.default_rng(0)
    texts = ["red cup", "chair", "nothing"]
    cols = [answer_cols(rng, 7), answer_cols(rng, 4), answer_cols(rng, 0)]
    inst = pb.Instance(
        id=0,
        centroid=[1, 2, 3],
        aabb=pb_box([1, 2, 3], [0.5, 0.5, 0.5]),
        obb=pb_box([1, 2, 3], [0.2, 0.4, 0.6], np.eye(3)[[1, 0, 2]]),
        score=0.7,
        num_members=12,
    )
    chunks = interleave(
        text_chunks(0, texts[0], cols[0], [inst], rows_per_chunk=3),
        text_chunks(1, texts[1], cols[1], rows_per_chunk=1),
        text_chunks(2, texts[2], cols[2]),
    )
    assert len(chunks) == 3 + 4 + 1
    answers = assemble_text_answers(chunks, texts, ["mean", "similarity", "instance"])
    assert [a.text for a in answers] == texts
    for a, c in zip(answers, cols, strict=True):
        for n, v in c.items():
            got = getattr(a, n)
            assert got.dtype == v.dtype and got.shape == v.shape
            np.testing.assert_array_equal(got, v)
        assert a.opacity is None and a.color is None  # not asked for
    assert answers[0].elapsed_ms == 1.5 and len(answers[0]) == 7
    (i0,) = answers[0].instances
    assert i0.num_members == 12 and i0.score == pytest.approx(0.7)
    np.testing.assert_array_equal(i0.aabb.rotation, np.eye(3))  # empty rotation: axis-aligned
    np.testing.assert_array_equal(i0.obb.rotation, np.eye(3)[[1, 0, 2]])
    assert answers[1].instances == () and answers[2].index.shape == (0,)
    # An empty answer still has the arrays that were asked for, empty and well shaped.
    (empty,) = assemble_text_answers(text_chunks(0, "e", answer_cols(rng, 0, False)), ["e"], ["color"])
    assert empty.color.shape == (0, 3) and empty.color.dtype == np.float32 and empty.mean is None


def test_text_answer_errors():
    rng = np.random.default_rng(1)
    good = text_chunks(0, "a", answer_cols(rng, 5), rows_per_chunk=2)
    with pytest.raises(ChunkError, match="starts at row 4, expected 2"):
        assemble_text_answers([good[0], good[2], good[1]], ["a"])
    with pytest.raises(ChunkError, match="announced 5"):
        assemble_text_answers(good[:2], ["a"])
    with pytest.raises(ChunkError, match=r"no answer for text\[1\]"):
        assemble_text_answers(good, ["a", "b"])
    with pytest.raises(ChunkError, match="out of range"):
        assemble_text_answers(good, [])
    bad = pb.TextQueryChunk()
    bad.CopyFrom(good[0])
    bad.mean.CopyFrom(to_tensor(np.zeros((1, 3), np.float32)))
    with pytest.raises(ChunkError, match=r"text\[0\]\.mean: 1 rows in a chunk of 2"):
        assemble_text_answers([bad, *good[1:]], ["a"])
    bad.mean.CopyFrom(to_tensor(np.zeros((2, 2), np.float32)))
    with pytest.raises(TensorError, match=r"text\[0\]\.mean"):
        assemble_text_answers([bad, *good[1:]], ["a"])
    # A field asked for but missing from a non-empty answer.
    with pytest.raises(ChunkError, match=r"text\[0\]\.opacity: 0 rows for 5"):
        assemble_text_answers(good, ["a"], ["opacity"])


def render_chunks(seq, images, rows_per_chunk, argmax=None, png=None):
    """Chunks of one rendered view: ``images`` maps names to [H,W,...] float32 arrays."""
    h, w = (next(iter(images.values())).shape[:2]) if images else (png["shape"])
    spans = row_chunks(h, 1, rows_per_chunk) if images else [(0, 0)]
    out = []
    for s, e in spans:
        c = pb.RenderChunk(sequence=seq, row_start=s)
        if s == 0:
            c.width, c.height, c.elapsed_ms = w, h, 2.5
            if argmax is not None:
                c.argmax.CopyFrom(pb.Pixel(x=argmax[0], y=argmax[1], value=argmax[2]))
            for n, data in (png or {}).items():
                if n != "shape":
                    setattr(c, f"{n}_png", data)
        for n, a in images.items():
            getattr(c, n).CopyFrom(to_tensor(a[s:e]))
        out.append(c)
    out[-1].last = True
    return out


def test_render_chunks_by_rows():
    rng = np.random.default_rng(2)
    h, w = 13, 7
    imgs = {
        "relevancy": rng.random((h, w)).astype(np.float32),
        "rgb": rng.random((h, w, 3)).astype(np.float32),
        "depth": rng.random((h, w)).astype(np.float32),
    }
    chunks = render_chunks(4, imgs, 5, argmax=(3, 9, 0.99))
    assert len(chunks) == 3
    r = assemble_render(chunks)
    assert (r.sequence, r.width, r.height, r.elapsed_ms) == (4, w, h, 2.5)
    for n, a in imgs.items():
        np.testing.assert_array_equal(getattr(r, n), a)
    assert r.alpha is None and r.png == {}
    assert (r.argmax.x, r.argmax.y, r.argmax.value) == (3, 9, 0.99)
    with pytest.raises(ChunkError, match="starts at row 10, expected 5"):
        assemble_render([chunks[0], chunks[2], chunks[1]])
    with pytest.raises(ChunkError, match="got 10 rows of 13"):
        assemble_render([chunks[0], chunks[1], pb.RenderChunk(sequence=4, last=True)])


def test_render_stream_interleaved_and_truncated():
    rng = np.random.default_rng(3)
    a = {"relevancy": rng.random((6, 4)).astype(np.float32)}
    b = {"relevancy": rng.random((6, 4)).astype(np.float32)}
    chunks = interleave(render_chunks(0, a, 2), render_chunks(1, b, 4))
    out = list(assemble_render_stream(chunks))
    assert [r.sequence for r in out] == [1, 0]  # in order of completion
    np.testing.assert_array_equal(out[1].relevancy, a["relevancy"])
    np.testing.assert_array_equal(out[0].relevancy, b["relevancy"])
    assert out[0].argmax is None
    with pytest.raises(ChunkError, match="before the last chunk"):
        list(assemble_render_stream(render_chunks(0, a, 2)[:-1]))


def test_render_png_encoding_is_decoded():
    rng = np.random.default_rng(4)
    rel8 = rng.integers(0, 256, (5, 6), dtype=np.uint8)
    rgb8 = rng.integers(0, 256, (5, 6, 3), dtype=np.uint8)
    depth16 = rng.integers(0, 65536, (5, 6), dtype=np.uint16)
    png = {
        "relevancy": encode_png(rel8),
        "rgb": encode_png(rgb8),
        "depth": encode_png(depth16),
        "shape": (5, 6),
    }
    r = assemble_render(render_chunks(0, {}, 1, png=png))
    np.testing.assert_allclose(r.relevancy, rel8 / 255, atol=1e-7)
    np.testing.assert_allclose(r.rgb, rgb8 / 255, atol=1e-7)
    np.testing.assert_allclose(r.depth, depth16 / 1000, rtol=1e-6)
    assert r.png["rgb"] == png["rgb"] and r.alpha is None
    bad = dict(png, relevancy=encode_png(rel8[:4]))
    with pytest.raises(ChunkError, match="relevancy_png"):
        assemble_render(render_chunks(0, {}, 1, png=bad))


def test_segment_chunks():
    labels = np.arange(12, dtype=np.int32).reshape(4, 3) % 3 - 1
    gi, gl = np.arange(5, dtype=np.int64) * 7, np.array([0, 1, 1, 0, 1], np.int32)
    c0 = pb.SegmentChunk(class_names=["a", "b"], width=3, height=4, elapsed_ms=1.0)
    c0.pixel_labels.CopyFrom(to_tensor(labels[:3]))
    c0.gaussian_index.CopyFrom(to_tensor(gi[:2]))
    c0.gaussian_labels.CopyFrom(to_tensor(gl[:2]))
    c1 = pb.SegmentChunk(last=True)
    c1.pixel_labels.CopyFrom(to_tensor(labels[3:]))
    c1.gaussian_index.CopyFrom(to_tensor(gi[2:]))
    c1.gaussian_labels.CopyFrom(to_tensor(gl[2:]))
    r = assemble_segment([c0, c1])
    # The same arrays sent one after the other (not row-aligned), as the server does.
    seq = [pb.SegmentChunk(class_names=["a", "b"], width=3, height=4)]
    for name, a, step in (("pixel_labels", labels, 3), ("gaussian_index", gi, 2), ("gaussian_labels", gl, 4)):
        for s0 in range(0, len(a), step):
            c = pb.SegmentChunk()
            getattr(c, name).CopyFrom(to_tensor(a[s0 : s0 + step]))
            seq.append(c)
    seq[-1].last = True
    r2 = assemble_segment([*seq, pb.SegmentChunk(class_names=["ignored after last"])])
    for n in ("pixel_labels", "gaussian_index", "gaussian_labels"):
        np.testing.assert_array_equal(getattr(r2, n), getattr(r, n))
    with pytest.raises(ChunkError, match="5 Gaussian indices but 4 labels"):
        assemble_segment(seq[:-1])
    assert r.class_names == ("a", "b")
    np.testing.assert_array_equal(r.pixel_labels, labels)
    np.testing.assert_array_equal(r.gaussian_index, gi)
    np.testing.assert_array_equal(r.gaussian_labels, gl)
    only_g = assemble_segment([pb.SegmentChunk(class_names=["a"], last=True)])
    assert only_g.pixel_labels is None and only_g.gaussian_index is None
    with pytest.raises(ChunkError, match=r"got \[3, 3\], expected \[4,3\]"):
        assemble_segment([c0, pb.SegmentChunk(last=True)])


def test_health_wire_format():
    health_pb2 = pytest.importorskip("grpc_health.v1.health_pb2")
    for service in ("", "fmgs.v1.Fmgs", "x" * 300):
        assert health_pb2.HealthCheckRequest.FromString(encode_health_request(service)).service == service
        assert (
            encode_health_request(service)
            == health_pb2.HealthCheckRequest(service=service).SerializeToString()
        )
    for status in (0, 1, 2, 3):
        data = health_pb2.HealthCheckResponse(status=status).SerializeToString()
        assert (
            decode_health_response(data) == ["UNKNOWN", "SERVING", "NOT_SERVING", "SERVICE_UNKNOWN"][status]
        )
    # Unknown fields of every wire type are skipped.
    extra = b"\x10\x05" + b"\x19" + b"\0" * 8 + b"\x22\x02ab" + b"\x2d" + b"\0" * 4
    assert decode_health_response(extra + b"\x08\x01") == "SERVING"
    with pytest.raises(ValueError):
        decode_health_response(b"\x08")


# ---------------------------------------------------------------- images and PLY


def _png_with_filters(img: np.ndarray, ftypes) -> bytes:
    """An 8-bit PNG whose rows use the given filter types (0-4 in turn), to exercise the decoder."""
    h = img.shape[0]
    bpp = 3 if img.ndim == 3 else 1
    rows = img.reshape(h, -1).astype(np.int64)
    raw = bytearray()
    prev = np.zeros(rows.shape[1], np.int64)
    for i in range(h):
        f = ftypes[i % len(ftypes)]
        x = rows[i]
        a = np.concatenate([np.zeros(bpp, np.int64), x[:-bpp]])
        c = np.concatenate([np.zeros(bpp, np.int64), prev[:-bpp]])
        if f == 0:
            pred = 0
        elif f == 1:
            pred = a
        elif f == 2:
            pred = prev
        elif f == 3:
            pred = (a + prev) // 2
        else:
            p = a + prev - c
            pa, pb_, pc = abs(p - a), abs(p - prev), abs(p - c)
            pred = np.where((pa <= pb_) & (pa <= pc), a, np.where(pb_ <= pc, prev, c))
        raw += bytes([f]) + ((x - pred) % 256).astype(np.uint8).tobytes()
        prev = x
    ihdr = struct.pack(">IIBBBBB", img.shape[1], h, 8, 2 if bpp == 3 else 0, 0, 0, 0)

    def chunk(k, d):
        return struct.pack(">I", len(d)) + k + d + struct.pack(">I", zlib.crc32(k + d))

    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(bytes(raw)))
        + chunk(b"IEND", b"")
    )


@pytest.mark.parametrize(
    "dtype, shape, mode",
    [(np.uint8, (17, 23), "L"), (np.uint8, (17, 23, 3), "RGB"), (np.uint16, (17, 23), "I;16")],
)
def test_png_writer_read_by_pillow(tmp_path, dtype, shape, mode):
    from PIL import Image

    rng = np.random.default_rng(5)
    img = rng.integers(0, np.iinfo(dtype).max + 1, shape).astype(dtype)
    path = write_png(tmp_path / "x.png", img)
    with Image.open(path) as im:
        assert im.mode == mode and im.size == (shape[1], shape[0])
        back = np.asarray(im)
    np.testing.assert_array_equal(back, img)
    for use_pillow in (False, True):
        np.testing.assert_array_equal(decode_png(path.read_bytes(), use_pillow), img)
    # PNGs from another encoder (pillow: adaptive filters) decode with the pure decoder too.
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG", optimize=True)
    for use_pillow in (False, True):
        back = decode_png(buf.getvalue(), use_pillow)
        assert back.dtype == img.dtype
        np.testing.assert_array_equal(back, img)


def test_png_decoder_all_filters():
    rng = np.random.default_rng(6)
    for img in (
        rng.integers(0, 256, (10, 9, 3), dtype=np.uint8),
        rng.integers(0, 256, (10, 9), dtype=np.uint8),
    ):
        np.testing.assert_array_equal(decode_png(_png_with_filters(img, [0, 1, 2, 3, 4]), False), img)
        np.testing.assert_array_equal(decode_png(_png_with_filters(img, [4, 3, 1]), False), img)
    with pytest.raises(ValueError, match="signature"):
        decode_png(b"GIF89a")
    with pytest.raises(ValueError, match="need uint8"):
        encode_png(np.zeros((2, 2), np.float32))


def test_colour_map():
    c = colorize(np.array([[-1.0, 0.0, 0.5], [1.0, 2.0, np.nan]]))
    assert c.shape == (2, 3, 3) and c.dtype == np.uint8
    np.testing.assert_array_equal(c[0, 0], c[0, 1])  # clipped below
    np.testing.assert_array_equal(c[1, 0], c[1, 1])  # clipped above
    np.testing.assert_array_equal(c[1, 2], c[0, 1])  # NaN -> lowest
    lo, hi = c[0, 1].astype(int), c[1, 0].astype(int)
    assert lo[2] > lo[0] and hi[0] > hi[2]  # blue-ish low end, red high end
    assert len({tuple(v) for v in colorize(np.linspace(0, 1, 50))}) > 40  # no flat stretches


def test_ply_round_trip(tmp_path):
    rng = np.random.default_rng(7)
    n = 50
    pts = rng.normal(size=(n, 3)).astype(np.float32)
    col = rng.integers(0, 256, (n, 3), dtype=np.uint8)
    rel = rng.random(n).astype(np.float32)
    idx = rng.integers(0, 10**6, n).astype(np.int64)
    path = write_ply(
        tmp_path / "p.ply", pts, col, {"relevancy": rel, "gaussian": idx, "d": rel.astype(">f8")}
    )
    back = read_ply(path)
    np.testing.assert_array_equal(back.points, pts)
    np.testing.assert_array_equal(back.colors, col)
    assert list(back.scalars) == ["relevancy", "gaussian", "d"]
    np.testing.assert_array_equal(back.scalars["relevancy"], rel)
    np.testing.assert_array_equal(back.scalars["gaussian"], idx)
    assert back.scalars["gaussian"].dtype == np.int32 and back.scalars["d"].dtype == np.float64
    empty = read_ply(write_ply(tmp_path / "e.ply", np.zeros((0, 3))))
    assert empty.points.shape == (0, 3) and empty.colors is None
    with pytest.raises(ValueError, match="must be"):
        write_ply(tmp_path / "bad.ply", pts, col, {"relevancy": rel[:3]})
    with pytest.raises(ValueError, match="int32"):
        write_ply(tmp_path / "bad.ply", pts, None, {"g": np.full(n, 2**40)})


# ---------------------------------------------------------------- cameras


@given(
    eye=hnp.arrays(np.float64, 3, elements=st.floats(-50, 50)),
    target=hnp.arrays(np.float64, 3, elements=st.floats(-50, 50)),
    up=st.sampled_from([(0, 0, 1), (0, -1, 0), (1, 1, 0)]),
)
def test_look_at(eye, target, up):
    if np.linalg.norm(target - eye) < 1e-3:
        return
    cam = CameraSpec.look_at(eye, target, up, width=64, height=48, fov_deg=70)
    R = cam.viewmat[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_array_equal(cam.viewmat[3], [0, 0, 0, 1])
    uv, z = cam.project(target[None])
    np.testing.assert_allclose(uv[0], [32, 24], atol=1e-6 * max(1, np.abs(eye).max()))
    assert z[0] == pytest.approx(np.linalg.norm(target - eye))
    np.testing.assert_allclose(cam.eye, eye, atol=1e-9 * max(1, np.abs(eye).max()))
    # Up in the world is up in the image (smaller y) unless looking along it.
    u = np.asarray(up, float) / np.linalg.norm(up)
    d = (target - eye) / np.linalg.norm(target - eye)
    if abs(d @ u) < 0.9:
        uv_up, _ = cam.project((target + 0.01 * np.linalg.norm(target - eye) * u)[None])
        assert uv_up[0, 1] < 24
    back = CameraSpec.from_proto(cam.to_proto())
    np.testing.assert_array_equal(back.viewmat, cam.viewmat)
    assert (back.fx, back.cx, back.width, back.height) == (cam.fx, cam.cx, 64, 48)


def test_look_at_degenerate():
    cam = CameraSpec.look_at((0, 0, 5), (0, 0, 0), (0, 0, 1))  # straight down along up
    R = cam.viewmat[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    with pytest.raises(ValueError, match="distinct"):
        CameraSpec.look_at((1, 1, 1), (1, 1, 1))
    with pytest.raises(ValueError, match="viewmat"):
        CameraSpec(np.eye(3), 1, 1, 1, 1, 2, 2)


# ---------------------------------------------------------------- Open3D helpers


def _answer_with_instances(n=400) -> TextAnswer:
    rng = np.random.default_rng(8)
    a = rng.normal(0, 0.1, (n // 2, 3)) + np.array([1, 0, 0])
    b = rng.normal(0, 0.1, (n - n // 2, 3)) + np.array([-1, 0.5, 0])
    mean = np.concatenate([a, b]).astype(np.float32)
    rel = np.linspace(0.95, 0.5, n).astype(np.float32)
    inst = np.r_[np.zeros(n // 2, np.int32), np.ones(n - n // 2, np.int32)]
    c, s = np.cos(0.4), np.sin(0.4)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    insts = tuple(
        Instance(
            k,
            p.mean(0),
            Box(p.mean(0), np.ptp(p, 0), np.eye(3)),
            Box(p.mean(0), np.ptp(p, 0) * 0.8, rot),
            0.8,
            len(p),
        )
        for k, p in enumerate((a, b))
    )
    return TextAnswer("thing", np.arange(n, dtype=np.int64), rel, mean=mean, instance=inst, instances=insts)


def test_open3d_export(tmp_path):
    o3d = pytest.importorskip("open3d")
    from fmgs_client import open3d_tools as ot

    ans = _answer_with_instances()
    geoms = ot.answer_geometries(ans)
    assert len(geoms) == 1 + 2 * len(ans.instances)
    paths = ot.export_answer(ans, tmp_path / "ans.ply")
    assert [p.name for p in paths] == ["ans.ply", "ans_boxes.ply"]
    pc = o3d.io.read_point_cloud(str(paths[0]))
    np.testing.assert_allclose(np.asarray(pc.points), ans.mean, atol=1e-6)
    np.testing.assert_allclose(np.asarray(pc.colors), colorize(ans.relevancy) / 255, atol=1e-6)
    ours = read_ply(paths[0])
    np.testing.assert_array_equal(ours.scalars["relevancy"], ans.relevancy)
    ls = o3d.io.read_line_set(str(paths[1]))
    assert len(ls.lines) == 12 * 2 * len(ans.instances) and len(ls.points) == 8 * 2 * len(ans.instances)
    np.testing.assert_allclose(np.asarray(ls.points)[:8].mean(0), ans.instances[0].aabb.center, atol=1e-9)
    with pytest.raises(ValueError, match="fields=\\['mean'\\]"):
        ot.export_answer(TextAnswer("x", np.zeros(0, np.int64), np.zeros(0, np.float32)), tmp_path / "n.ply")


def test_numpy_screenshot_fallback(tmp_path):
    from fmgs_client import open3d_tools as ot

    ans = _answer_with_instances()
    path = ot.screenshot(ans, tmp_path / "s.png", 160, 120, method="numpy")
    img = decode_png(path.read_bytes())
    assert img.shape == (120, 160, 3)
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 20  # points in many colours, boxes, background
    # The first instance's centroid lands where the camera projects it.
    cam = ot.view_camera(ans, 160, 120)
    uv, _ = cam.project(ans.instances[0].centroid[None])
    x, y = np.floor(uv[0]).astype(int)
    assert (img[y - 3 : y + 4, x - 3 : x + 4] != 255).any()


_SHOT = """
import sys, numpy as np
sys.path.insert(0, {tests!r})
from test_client_unit import _answer_with_instances
from fmgs_client import open3d_tools as ot
ot.screenshot(_answer_with_instances(), {out!r}, 160, 120, method="open3d")
"""


def test_open3d_headless_screenshot(tmp_path):
    pytest.importorskip("open3d")
    import ctypes.util

    if ctypes.util.find_library("vulkan") is None:
        pytest.skip("no libvulkan (Debian libvulkan1 mesa-vulkan-drivers): Open3D cannot render headless")
    out = tmp_path / "shot.png"
    # A subprocess: Filament aborts the whole process when it finds no usable device.
    code = _SHOT.format(tests=str(Path(__file__).parent), out=str(out))
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    img = decode_png(out.read_bytes())
    assert img.shape == (120, 160, 3)
    colours = np.unique(img.reshape(-1, 3), axis=0)
    assert len(colours) > 20 and (img == 255).all(-1).mean() > 0.5  # white background, coloured points
    # Open3D and the numpy fallback use the same camera: the painted pixels overlap.
    ot = pytest.importorskip("fmgs_client.open3d_tools")
    soft = decode_png(
        ot.screenshot(_answer_with_instances(), tmp_path / "n.png", 160, 120, method="numpy").read_bytes()
    )
    a, b = (img != 255).any(-1), (soft != 255).any(-1)
    assert (a & b).sum() / (a | b).sum() > 0.3


# ---------------------------------------------------------------- import hygiene


def test_client_imports_without_torch():
    code = (
        "import sys; sys.modules['torch'] = None\n"
        "import fmgs_client, fmgs_client.client, fmgs_client.cli, fmgs_client.types\n"
        "import fmgs_client.open3d_tools, fmgs_wire.images, fmgs_client.ply\n"
        "bad = [m for m in ('fmgs', 'torch', 'open3d', 'PIL', 'plyfile', 'rich') if sys.modules.get(m)]\n"
        "assert not bad, bad\n"
        "print('ok')\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr


# ---------------------------------------------------------------- against an in-process fake service

SCENE = pb.SceneInfo(
    name="demo",
    state=pb.SCENE_STATE_READY,
    encoder_id="enc",
    embedding_dim=8,
    num_gaussians=1000,
    num_embedded=400,
    canonical_phrases=["object", "stuff"],
    version="v1",
    bounds=[-1, -1, 0, 1, 1, 0.5],
)


class FakeFmgs(pb_grpc.FmgsServicer):
    """Just enough of the service to drive the client: fixed answers, chunked like the real one."""

    def __init__(self) -> None:
        self.auth: list[str | None] = []
        self.requests: list = []

    def _check(self, context, scene=None):
        self.auth.append(dict(context.invocation_metadata()).get("authorization"))
        if scene is not None and scene != "demo":
            context.abort(grpc.StatusCode.NOT_FOUND, f"no scene {scene!r}")

    def ListScenes(self, request, context):
        self._check(context)
        return pb.ListScenesResponse(scenes=[SCENE, pb.SceneInfo(name="broken", state=4, reason="bad file")])

    def GetScene(self, request, context):
        self._check(context, request.scene)
        return SCENE

    def TextQuery(self, request, context):
        self._check(context, request.scene)
        self.requests.append(request)
        rng = np.random.default_rng(0)
        lists = []
        for i, t in enumerate(request.texts):
            cols = answer_cols(rng, min(request.top_k, 9))
            names = {pb.GaussianField.Name(f).removeprefix("GAUSSIAN_FIELD_").lower() for f in request.fields}
            cols = {n: v for n, v in cols.items() if n in ("index", "relevancy") or n in names}
            insts = []
            if request.instances.enabled:
                insts = [
                    pb.Instance(
                        id=0,
                        centroid=[0, 0, 0],
                        aabb=pb_box([0, 0, 0], [1, 1, 1]),
                        obb=pb_box([0, 0, 0], [1, 1, 1]),
                        score=0.5,
                        num_members=3,
                    )
                ]
            lists.append(text_chunks(i, t, cols, insts, rows_per_chunk=4))
        yield from interleave(*lists)

    def _render(self, request):
        cam = request.camera
        h, w = cam.height, cam.width
        rel = (np.arange(h * w, dtype=np.float32).reshape(h, w) / (h * w)).astype(np.float32)
        imgs = {"relevancy": rel}
        if pb.RENDER_OUTPUT_RGB in request.outputs:
            imgs["rgb"] = np.repeat(rel[..., None], 3, -1)
        return render_chunks(request.sequence, imgs, 3, argmax=(w - 1, h - 1, float(rel.max())))

    def Render(self, request, context):
        self._check(context, request.scene)
        if not request.text:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, "text: required for relevancy")
        yield from self._render(request)

    def StreamRender(self, request_iterator, context):
        self._check(context)
        for req in request_iterator:
            self.requests.append(req)
            yield from self._render(req)

    def PointQuery(self, request, context):
        self._check(context, request.scene)
        p = from_tensor(request.points, "points")
        rel = np.tile(p[:, 0].astype(np.float32), (len(request.texts), 1))
        return pb.PointQueryResponse(relevancy=to_tensor(rel), similarity=to_tensor(rel), elapsed_ms=1.0)

    def Segment(self, request, context):
        self._check(context, request.scene)
        c = pb.SegmentChunk(class_names=request.class_names, last=True)
        if request.HasField("camera"):
            c.width, c.height = request.camera.width, request.camera.height
            c.pixel_labels.CopyFrom(to_tensor(np.zeros((c.height, c.width), np.int32)))
        c.gaussian_index.CopyFrom(to_tensor(np.arange(3, dtype=np.int64)))
        c.gaussian_labels.CopyFrom(to_tensor(np.array([0, 1, 0], np.int32)))
        yield c

    def LoadScene(self, request, context):
        self._check(context, request.scene)
        return SCENE


@pytest.fixture(scope="module")
def fake():
    server = grpc.server(futures.ThreadPoolExecutor(4))
    svc = FakeFmgs()
    pb_grpc.add_FmgsServicer_to_server(svc, server)
    try:
        from grpc_health.v1 import health, health_pb2, health_pb2_grpc

        hs = health.HealthServicer()
        hs.set("", health_pb2.HealthCheckResponse.SERVING)
        hs.set("fmgs.v1.Fmgs", health_pb2.HealthCheckResponse.NOT_SERVING)
        health_pb2_grpc.add_HealthServicer_to_server(hs, server)
    except ImportError:
        pass
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    yield svc, f"127.0.0.1:{port}"
    server.stop(None)


def test_client_against_fake(fake):
    svc, address = fake
    with FmgsClient(address, token="s3cret", timeout=10) as c:
        scenes = c.list_scenes()
        assert [s.state for s in scenes] == ["ready", "failed"] and scenes[1].reason == "bad file"
        info = c.scene("demo")
        np.testing.assert_array_equal(info.bounds, [[-1, -1, 0], [1, 1, 0.5]])
        assert info.canonical_phrases == ("object", "stuff")
        with pytest.raises(FmgsError) as e:
            c.scene("nope")
        assert e.value.code == "NOT_FOUND" and "nope" in e.value.details
        answers = c.query("demo", ["a", "b"], top_k=6, fields=["mean"], instances={"eps": 0.1})
        req = svc.requests[-1]
        assert req.instances.enabled and req.instances.eps == 0.1 and pb.GAUSSIAN_FIELD_INSTANCE in req.fields
        assert [len(a) for a in answers] == [6, 6] and answers[0].mean.shape == (6, 3)
        assert answers[1].instance.dtype == np.int32 and len(answers[1].instances) == 1
        cam = CameraSpec.look_at((0, -3, 1), (0, 0, 0), width=8, height=7)
        r = c.render("demo", cam, "a", outputs=("relevancy", "rgb"))
        assert r.relevancy.shape == (7, 8) and r.rgb.shape == (7, 8, 3) and r.argmax.x == 7
        with pytest.raises(FmgsError, match="INVALID_ARGUMENT: text"):
            c.render("demo", cam, "")
        cams = [CameraSpec.look_at((0, -3, k), (0, 0, 0), width=4, height=5) for k in range(5)]
        seqs = [x.sequence for x in c.stream("demo", iter(cams), "a")]
        assert seqs == [0, 1, 2, 3, 4]
        assert [q.sequence for q in svc.requests[-5:]] == [0, 1, 2, 3, 4]
        with pytest.raises(TypeError, match="CameraSpec"):
            list(c.stream("demo", [cams[0], "not a camera"], "a"))
        p = c.points("demo", ["a", "b", "c"], np.array([[1.0, 2, 3], [4, 5, 6]]))
        assert p.relevancy.shape == (3, 2) and p.relevancy[2, 1] == 4
        s = c.segment("demo", ["x", "y"], camera=cam)
        assert s.pixel_labels.shape == (7, 8) and list(s.gaussian_labels) == [0, 1, 0]
        assert c.load("demo").name == "demo"
        with pytest.raises(FmgsError) as e:
            c.unload("demo")
        assert e.value.code == "UNIMPLEMENTED"
        if HAS_HEALTH:
            assert c.health() == "SERVING" and c.health("fmgs.v1.Fmgs") == "NOT_SERVING"
            with pytest.raises(FmgsError, match="NOT_FOUND"):
                c.health("other")
    assert set(svc.auth) == {"Bearer s3cret"}
    with FmgsClient(address) as c:
        c.list_scenes()
    assert svc.auth[-1] is None


def test_unreachable_server_is_an_fmgs_error():
    with FmgsClient("127.0.0.1:1", timeout=2) as c, pytest.raises(FmgsError) as e:
        c.list_scenes()
    assert e.value.code in ("UNAVAILABLE", "DEADLINE_EXCEEDED")


def test_cli_against_fake(fake, tmp_path, capsys):
    _, address = fake
    base = ["--address", address, "--timeout", "10"]
    assert cli.main([*base, "list"]) == 0
    out = capsys.readouterr().out
    assert "demo" in out and "ready" in out and "bad file" in out
    assert cli.main([*base, "info", "demo"]) == 0
    assert "object, stuff" in capsys.readouterr().out
    ply = tmp_path / "q.ply"
    assert (
        cli.main([*base, "query", "demo", "red cup", "--top-k", "5", "--instances", "--ply", str(ply)]) == 0
    )
    out = capsys.readouterr().out
    assert "'red cup': 5 Gaussians" in out and "1 instances" in out and "relevancy" in out
    back = read_ply(ply)
    assert back.points.shape == (5, 3) and "relevancy" in back.scalars and back.colors is not None
    png, rgb = tmp_path / "r.png", tmp_path / "rgb.png"
    assert (
        cli.main([*base, "render", "demo", "cup", "--size", "12x9", "--out", str(png), "--rgb", str(rgb)])
        == 0
    )
    out = capsys.readouterr().out
    assert "argmax pixel x=11 y=8" in out
    assert decode_png(png.read_bytes()).shape == (9, 12, 3) and decode_png(rgb.read_bytes()).shape == (
        9,
        12,
        3,
    )
    eye = ["--eye", "0", "-3", "1", "--target", "0", "0", "0"]
    assert cli.main([*base, "render", "demo", "cup", *eye, "--size", "4x4", "--out", str(png)]) == 0
    capsys.readouterr()
    assert cli.main([*base, "stream", "demo", "cup", "--frames", "6", "--size", "8x6"]) == 0
    assert "6 of 6 poses" in capsys.readouterr().out
    assert cli.main([*base, "segment", "demo", "x", "y", "--out", str(tmp_path / "seg.png")]) == 0
    assert "gaussians" in capsys.readouterr().out and (tmp_path / "seg.png").is_file()
    # Errors: one line on stderr, status 1.
    assert cli.main([*base, "info", "nope"]) == 1
    err = capsys.readouterr().err
    assert err.strip() == "error: NOT_FOUND: no scene 'nope'"
    assert cli.main([*base, "render", "demo", "", "--out", str(png)]) == 1
    assert capsys.readouterr().err.startswith("error: INVALID_ARGUMENT: ")
    assert cli.main(["--address", "127.0.0.1:1", "--timeout", "2", "list"]) == 1
    assert capsys.readouterr().err.startswith("error: ")


def test_cli_health(fake, capsys):
    pytest.importorskip("grpc_health.v1.health")
    _, address = fake
    assert cli.main(["--address", address, "health"]) == 0
    assert capsys.readouterr().out.strip() == "SERVING"
    assert cli.main(["--address", address, "health", "fmgs.v1.Fmgs"]) == 1
    assert capsys.readouterr().out.strip() == "NOT_SERVING"


def test_cli_token_file(fake, tmp_path, capsys):
    svc, address = fake
    tok = tmp_path / "token"
    tok.write_text("abc\n")
    assert cli.main(["--address", address, "--token-file", str(tok), "list"]) == 0
    assert svc.auth[-1] == "Bearer abc"
    capsys.readouterr()
