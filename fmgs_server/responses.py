"""Answers to messages: scene descriptions and the chunked streams of text, render and segment answers.

Every stream is split by rows so that no message exceeds ``chunk_bytes`` of payload (fmgs_wire.tensors).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from fmgs.cameras import Camera
from fmgs.query.engine import SceneEngine, TextAnswer
from fmgs.query.pose import PoseRender
from fmgs.query.segment import Segmentation
from fmgs.scene.manifest import Manifest
from fmgs_server import convert
from fmgs_server.repository import FAILED, LOADING, READY, UNLOADED, SceneSlot
from fmgs_wire.images import encode_output_png
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.tensors import row_chunks, to_tensor

STATES = {
    UNLOADED: pb.SCENE_STATE_UNLOADED,
    LOADING: pb.SCENE_STATE_LOADING,
    READY: pb.SCENE_STATE_READY,
    FAILED: pb.SCENE_STATE_FAILED,
}

COLUMNS = {
    pb.GAUSSIAN_FIELD_MEAN: "mean",
    pb.GAUSSIAN_FIELD_OPACITY: "opacity",
    pb.GAUSSIAN_FIELD_SCALE: "scale",
    pb.GAUSSIAN_FIELD_ROTATION: "rotation",
    pb.GAUSSIAN_FIELD_COLOR: "color",
}
"""Wire fields of a text answer that are per-Gaussian attributes (computed by the engine)."""


def scene_info(slot: SceneSlot, manifest: Manifest | None) -> pb.SceneInfo:
    """A scene's state, and what its manifest says (the loaded version's when it is loaded; nothing more
    than the state when the manifest cannot be read: loading will report why)."""
    info = pb.SceneInfo(name=slot.name, state=STATES[slot.state], reason=slot.reason, version=slot.version)
    e = slot.engine
    m = e.manifest if e is not None else manifest
    if m is None:
        return info
    info.encoder_id, info.embedding_dim = m.encoder_id, m.dim
    info.num_gaussians, info.num_embedded = m.num_gaussians, m.num_selected
    info.sh_degree, info.has_field = m.sh_degree, m.field is not None
    info.canonical_phrases.extend(m.canonical)
    info.label_names.extend(m.label_names)
    info.bounds.extend(m.bounds if e is None else (float(v) for v in e.bounds))
    info.frame_id = m.frame_id
    if e is not None:
        info.resident_bytes = e.nbytes()
    return info


def text_chunks(
    engine: SceneEngine,
    i: int,
    text: str,
    a: TextAnswer,
    fields: set[int],
    ms: float,
    chunk_bytes: int,
    negatives: tuple[str, ...] = (),
) -> Iterator[pb.TextQueryChunk]:
    """The chunks of text ``i``'s answer: index and relevancy always, the asked-for columns, presence
    (its rival named from ``negatives``) when it was computed."""
    idx = a.index
    cols: dict[str, np.ndarray] = {"index": idx.numpy(), "relevancy": a.relevancy.numpy()}
    if pb.GAUSSIAN_FIELD_SIMILARITY in fields:
        cols["similarity"] = a.similarity.numpy()
    names = [n for f, n in COLUMNS.items() if f in fields]
    carried = a.columns
    cols.update(engine.gaussian_columns(idx, names) if carried is None else {n: carried[n] for n in names})
    if pb.GAUSSIAN_FIELD_INSTANCE in fields:
        ids = a.instance_ids if a.instance_ids is not None else np.full(len(idx), -1, np.int32)
        cols["instance"] = ids.astype(np.int32)
    row_bytes = sum(c.itemsize * (c.size // max(1, len(c))) for c in cols.values())
    for n, (s, e) in enumerate(row_chunks(len(idx), row_bytes, chunk_bytes)):
        chunk = pb.TextQueryChunk(text_index=i, start=s)
        if n == 0:
            chunk.text, chunk.total, chunk.elapsed_ms = text, len(idx), ms
            chunk.rescored = a.rescored
            if a.presence is not None:
                p = a.presence
                rival = negatives[p.rival] if 0 <= p.rival < len(negatives) else ""
                chunk.presence.CopyFrom(
                    pb.Presence(score=p.score, found=p.found, margin=p.margin, rival=rival)
                )
            chunk.instances.extend(convert.instance(j, x) for j, x in enumerate(a.instances))
        for name, c in cols.items():
            getattr(chunk, name).CopyFrom(to_tensor(c[s:e]))
        yield chunk


def render_chunks(
    seq: int, cam: Camera, out: PoseRender, encoding: int, ms: float, chunk_bytes: int
) -> Iterator[pb.RenderChunk]:
    """One PNG message, or float32 images split by rows; the first carries size, argmax and timing."""
    W, H = cam.width, cam.height
    first = pb.RenderChunk(sequence=seq, width=W, height=H, elapsed_ms=ms)
    if out.argmax is not None:
        x, y, v = out.argmax
        first.argmax.CopyFrom(pb.Pixel(x=x, y=y, value=v))
    imgs = {k: getattr(out, k) for k in ("relevancy", "rgb", "depth", "alpha") if getattr(out, k) is not None}
    if encoding == pb.IMAGE_ENCODING_PNG:
        for k, v in imgs.items():
            setattr(first, f"{k}_png", encode_output_png(k, v.numpy()))
        first.last = True
        yield first
        return
    arrays = {k: v.numpy().astype(np.float32) for k, v in imgs.items()}
    row_bytes = sum(a.itemsize * a[0].size for a in arrays.values()) if arrays else 1
    ranges = row_chunks(H, row_bytes, chunk_bytes)
    for n, (s, e) in enumerate(ranges):
        chunk = first if n == 0 else pb.RenderChunk(sequence=seq)
        chunk.row_start = s
        for k, a in arrays.items():
            getattr(chunk, k).CopyFrom(to_tensor(a[s:e]))
        chunk.last = n == len(ranges) - 1
        yield chunk


def segment_chunks(
    names: list[str], cam: Camera | None, s: Segmentation, ms: float, chunk_bytes: int
) -> list[pb.SegmentChunk]:
    """The first chunk carries the description; then one chunk per slice of one array."""
    first = pb.SegmentChunk(class_names=names, elapsed_ms=ms)
    parts: list[tuple[str, np.ndarray]] = []
    if s.pixel_labels is not None and cam is not None:
        first.width, first.height = cam.width, cam.height
        parts.append(("pixel_labels", s.pixel_labels.numpy()))
    if s.gaussian_labels is not None:
        parts += [
            ("gaussian_index", s.gaussian_index.numpy()),
            ("gaussian_labels", s.gaussian_labels.numpy()),
        ]
    chunks = [first]
    for name, a in parts:
        row = a.itemsize * (a[0].size if len(a) else 1)
        for s0, e in row_chunks(len(a), row, chunk_bytes):
            c = pb.SegmentChunk()
            getattr(c, name).CopyFrom(to_tensor(a[s0:e]))
            chunks.append(c)
    chunks[-1].last = True
    return chunks


def geometry_chunks(
    engine: SceneEngine,
    index: np.ndarray,
    qualified: int,
    cols: dict[str, np.ndarray],
    ms: float,
    chunk_bytes: int,
) -> Iterator[pb.GeometryChunk]:
    """The chunks of a geometry answer: the first describes it, every one carries consecutive rows of the
    index and of each column; the last is marked."""
    arrays = {"index": index, **cols}
    row_bytes = sum(a.itemsize * (a.size // max(1, len(a))) for a in arrays.values())
    ranges = row_chunks(len(index), row_bytes, chunk_bytes)
    for n, (s, e) in enumerate(ranges):
        chunk = pb.GeometryChunk(start=s, last=n == len(ranges) - 1)
        if n == 0:
            chunk.num_gaussians, chunk.qualified, chunk.total = engine.num_gaussians, qualified, len(index)
            chunk.bounds.extend(float(v) for v in engine.bounds)
            chunk.elapsed_ms = ms
        for name, a in arrays.items():
            getattr(chunk, name).CopyFrom(to_tensor(a[s:e]))
        yield chunk
