"""Chunk reassembly of the thin client (``fmgs_client.client``'s plain functions) on hand-built chunks:
interleaved and out-of-order text answers, rendered rows and PNGs, segment arrays."""

from __future__ import annotations

import numpy as np
import pytest

from fmgs_client.client import (
    ChunkError,
    assemble_render,
    assemble_render_stream,
    assemble_segment,
    assemble_text_answers,
)
from fmgs_wire.images import encode_png
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.tensors import TensorError, to_tensor
from tests.helpers.client_fakes import answer_cols, interleave, pb_box, render_chunks, text_chunks


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
    # Presence: absent (an older server) is None; a score outside [0,1] or a NaN margin is refused.
    (plain,) = assemble_text_answers(good, ["a"])
    assert plain.presence is None and plain.found is None
    ok = pb.TextQueryChunk()
    ok.CopyFrom(good[0])
    ok.presence.CopyFrom(pb.Presence(score=0.2, found=False, margin=-0.14, rival="mug"))
    (a,) = assemble_text_answers([ok, *good[1:]], ["a"])
    assert a.found is False and a.presence.rival == "mug" and a.presence.margin == -0.14
    for score, margin in ((1.5, 0.1), (0.5, float("nan")), (-0.1, 0.0)):
        ok.presence.CopyFrom(pb.Presence(score=score, found=True, margin=margin, rival="x"))
        with pytest.raises(ChunkError, match=r"text\[0\]: presence"):
            assemble_text_answers([ok, *good[1:]], ["a"])


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
