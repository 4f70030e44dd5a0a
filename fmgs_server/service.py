"""The ``fmgs.v1.Fmgs`` service: validates requests, runs the query engine, streams chunked answers."""

from __future__ import annotations

import functools
import json
import logging
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import grpc
import numpy as np
import torch

from fmgs.errors import FmgsError, ValidationError
from fmgs.query.points import NoFieldError, query_points
from fmgs.query.pose import render_pose
from fmgs.query.segment import segment
from fmgs_server import convert
from fmgs_server.config import ServerConfig
from fmgs_server.encoders import EncoderCache
from fmgs_server.errors import (
    DeadlineExceeded,
    FailedPrecondition,
    InvalidArgument,
    ResourceExhausted,
    ServiceError,
)
from fmgs_server.repository import FAILED, LOADING, READY, UNLOADED, SceneRepository
from fmgs_wire.images import encode_output_png
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc
from fmgs_wire.tensors import row_chunks, to_tensor

log = logging.getLogger("fmgs_server")

_STATES = {
    UNLOADED: pb.SCENE_STATE_UNLOADED,
    LOADING: pb.SCENE_STATE_LOADING,
    READY: pb.SCENE_STATE_READY,
    FAILED: pb.SCENE_STATE_FAILED,
}


def _status(e: BaseException) -> tuple[grpc.StatusCode, str]:
    """The status code and message for an exception raised while answering."""
    if isinstance(e, ServiceError):
        return e.code, e.message
    if isinstance(e, NoFieldError):
        return grpc.StatusCode.FAILED_PRECONDITION, str(e)
    if isinstance(e, ValidationError):
        return grpc.StatusCode.INVALID_ARGUMENT, str(e)
    if isinstance(e, FmgsError):
        return grpc.StatusCode.FAILED_PRECONDITION, str(e)
    if isinstance(e, MemoryError):
        return grpc.StatusCode.RESOURCE_EXHAUSTED, "out of memory answering this request"
    return grpc.StatusCode.INTERNAL, "internal error (see the server log)"


def _scene_of(request) -> str:
    return getattr(request, "scene", "") if not isinstance(request, Iterator) else ""


def rpc(fn):
    """Unary handler: map errors to status codes, log one line with timing."""

    @functools.wraps(fn)
    def wrapper(self, request, context):
        t0 = time.perf_counter()
        code = grpc.StatusCode.OK
        try:
            return fn(self, request, context)
        except Exception as e:
            code, msg = _status(e)
            if code == grpc.StatusCode.INTERNAL:
                log.exception("%s failed", fn.__name__)
            context.abort(code, msg)
        finally:
            log.info(
                "%s scene=%s %s %.1f ms",
                fn.__name__,
                _scene_of(request),
                code.name,
                (time.perf_counter() - t0) * 1e3,
            )

    return wrapper


def rpc_stream(fn):
    """Streaming handler: as ``rpc`` for generators; stops quietly when the client has gone."""

    @functools.wraps(fn)
    def wrapper(self, request, context):
        t0 = time.perf_counter()
        code, n = grpc.StatusCode.OK, 0
        try:
            for msg in fn(self, request, context):
                if not context.is_active():
                    code = grpc.StatusCode.CANCELLED
                    return
                n += 1
                yield msg
        except Exception as e:
            code, text = _status(e)
            if code == grpc.StatusCode.INTERNAL:
                log.exception("%s failed", fn.__name__)
            context.abort(code, text)
        finally:
            log.info(
                "%s scene=%s %s %d msgs %.1f ms",
                fn.__name__,
                _scene_of(request),
                code.name,
                n,
                (time.perf_counter() - t0) * 1e3,
            )

    return wrapper


_COLUMNS = {
    pb.GAUSSIAN_FIELD_MEAN: "mean",
    pb.GAUSSIAN_FIELD_OPACITY: "opacity",
    pb.GAUSSIAN_FIELD_SCALE: "scale",
    pb.GAUSSIAN_FIELD_ROTATION: "rotation",
    pb.GAUSSIAN_FIELD_COLOR: "color",
}
"""Wire fields of a text answer that are per-Gaussian attributes (computed by the engine)."""


class FmgsService(pb_grpc.FmgsServicer):
    """The service over a scene repository and a text-encoder cache."""

    def __init__(self, cfg: ServerConfig, repo: SceneRepository, encoders: EncoderCache) -> None:
        self.cfg = cfg
        self.repo = repo
        self.encoders = encoders
        self._slots = threading.BoundedSemaphore(cfg.compute_slots)
        self._streams = threading.BoundedSemaphore(cfg.max_streams)

    # ------------------------------------------------------------------ helpers

    @contextmanager
    def _compute(self, context, patient: bool = False):
        """A compute slot, waited for at most queue_timeout_s (and never past the deadline).

        ``patient`` (pose streams): wait as long as the client is there; a stream's next frame simply
        comes later, and its newest pose replaces any it could not render meanwhile.
        """
        if patient:
            while not self._slots.acquire(timeout=0.25):
                if not context.is_active():
                    raise ResourceExhausted("the client went away while waiting for a compute slot")
        else:
            wait = self.cfg.queue_timeout_s
            left = context.time_remaining()
            if left is not None:
                if left <= 0:
                    raise DeadlineExceeded("the deadline passed before the work could start")
                wait = min(wait, left)
            if not self._slots.acquire(timeout=wait):
                left = context.time_remaining()
                if left is not None and left <= 0:
                    raise DeadlineExceeded("the deadline passed while waiting for a compute slot")
                raise ResourceExhausted("server busy: no compute slot free; retry later")
        try:
            yield
        finally:
            self._slots.release()

    def _canonical(self, engine, phrases) -> torch.Tensor | None:
        phrases = convert.texts(phrases, self.cfg, "canonical_phrases", allow_empty=True)
        return self.encoders.embed(engine.encoder_id, phrases) if phrases else None

    def _info(self, slot) -> pb.SceneInfo:
        info = pb.SceneInfo(
            name=slot.name, state=_STATES[slot.state], reason=slot.reason, version=slot.version
        )
        e = slot.engine
        if e is None:
            try:
                m = json.loads((self.repo.root / slot.name / "manifest.json").read_text())
                info.encoder_id = str(m["encoder"]["id"])
                info.embedding_dim = int(m["encoder"]["dim"])
                info.num_gaussians = int(m["counts"]["gaussians"])
                info.num_embedded = int(m["counts"]["selected"])
                info.sh_degree = int(m.get("sh_degree", 0))
                info.has_field = bool(m.get("field"))
                info.canonical_phrases.extend(str(c) for c in m["canonical"])
                info.label_names.extend(str(c) for c in (m.get("extra") or {}).get("label_names", []))
                b = m.get("bounds")
                if isinstance(b, list) and len(b) == 6:
                    info.bounds.extend(float(v) for v in b)
            except (OSError, ValueError, KeyError, TypeError):
                pass  # a broken manifest shows as FAILED once loading is tried
            return info
        info.encoder_id, info.embedding_dim = e.encoder_id, e.dim
        info.num_gaussians, info.num_embedded = e.num_gaussians, e.num_embedded
        info.sh_degree, info.has_field = e.gaussians.sh_degree, e.field is not None
        info.canonical_phrases.extend(e.canonical_phrases)
        info.label_names.extend(str(c) for c in (e.manifest.get("extra") or {}).get("label_names", []))
        info.resident_bytes = e.nbytes()
        info.bounds.extend(float(v) for v in e.bounds)
        return info

    # ------------------------------------------------------------------ scenes

    @rpc
    def ListScenes(self, request, context):
        return pb.ListScenesResponse(scenes=[self._info(s) for s in self.repo.scan()])

    @rpc
    def GetScene(self, request, context):
        return self._info(self.repo.slot(request.scene))

    @rpc
    def LoadScene(self, request, context):
        with self._compute(context):
            return self._info(self.repo.load(request.scene))

    @rpc
    def UnloadScene(self, request, context):
        return self._info(self.repo.unload(request.scene))

    @rpc
    def ReloadScene(self, request, context):
        with self._compute(context):
            return self._info(self.repo.reload(request.scene))

    # ------------------------------------------------------------------ text query

    @rpc_stream
    def TextQuery(self, request, context):
        cfg = self.cfg
        values = convert.texts(request.texts, cfg)
        k = convert.top_k(request.top_k, cfg)
        thr = convert.threshold(request.threshold)
        fields = set(request.fields)
        inst_cfg = convert.instance_config(request.instances) if request.instances.enabled else None
        engine = self.repo.get(request.scene)
        with self._compute(context):
            if request.HasField("embeddings"):
                if request.encoder_id != engine.encoder_id:
                    raise FailedPrecondition(
                        f"encoder_id: {request.encoder_id!r} differs from the scene's {engine.encoder_id!r}"
                    )
                q = convert.tensor(request.embeddings, "embeddings", (len(values), engine.dim), cfg.max_texts)
            else:
                q = self.encoders.embed(engine.encoder_id, values)
            canon = self._canonical(engine, request.canonical_phrases)
            answers = []
            for i, text in enumerate(values):
                t0 = time.perf_counter()
                a = engine.text_query(q[i], k, thr, canon, inst_cfg)
                answers.append((i, text, a, (time.perf_counter() - t0) * 1e3))
        for i, text, a, ms in answers:
            yield from self._text_chunks(engine, i, text, a, fields, ms)

    def _text_chunks(self, engine, i, text, a, fields, ms):
        idx = a.index
        cols: dict[str, np.ndarray] = {"index": idx.numpy(), "relevancy": a.relevancy.numpy()}
        if pb.GAUSSIAN_FIELD_SIMILARITY in fields:
            cols["similarity"] = a.similarity.numpy()
        cols.update(engine.gaussian_columns(idx, [n for f, n in _COLUMNS.items() if f in fields]))
        if pb.GAUSSIAN_FIELD_INSTANCE in fields:
            ids = a.instance_ids if a.instance_ids is not None else np.full(len(idx), -1, np.int32)
            cols["instance"] = ids.astype(np.int32)
        row_bytes = sum(c.itemsize * (c.size // max(1, len(c))) for c in cols.values())
        for n, (s, e) in enumerate(row_chunks(len(idx), row_bytes, self.cfg.chunk_bytes)):
            chunk = pb.TextQueryChunk(text_index=i, start=s)
            if n == 0:
                chunk.text, chunk.total, chunk.elapsed_ms = text, len(idx), ms
                chunk.instances.extend(convert.instance(j, x) for j, x in enumerate(a.instances))
            for name, c in cols.items():
                getattr(chunk, name).CopyFrom(to_tensor(c[s:e]))
            yield chunk

    # ------------------------------------------------------------------ render

    def _render_request(self, request, context, patient: bool = False) -> Iterator[pb.RenderChunk]:
        cfg = self.cfg
        cam = convert.camera(request.camera, cfg, request.HasField("camera"))
        outputs = tuple(dict.fromkeys(convert.OUTPUT_NAMES.get(o, "?") for o in request.outputs)) or (
            "relevancy",
        )
        if "?" in outputs:
            raise InvalidArgument(f"outputs: unknown value in {list(request.outputs)}")
        encoding = request.encoding or pb.IMAGE_ENCODING_FLOAT32
        if encoding not in (pb.IMAGE_ENCODING_FLOAT32, pb.IMAGE_ENCODING_PNG):
            raise InvalidArgument(f"encoding: unknown value {encoding}")
        engine = self.repo.get(request.scene)
        with self._compute(context, patient):
            t0 = time.perf_counter()
            q = None
            if "relevancy" in outputs:
                values = convert.texts([request.text] if request.text else [], cfg, "text")
                q = self.encoders.embed(engine.encoder_id, values)[0]
            canon = self._canonical(engine, request.canonical_phrases)
            out = render_pose(engine, cam, q, outputs, canon)
            ms = (time.perf_counter() - t0) * 1e3
        yield from self._render_chunks(request.sequence, cam, out, encoding, ms)

    def _render_chunks(self, seq, cam, out, encoding, ms):
        W, H = cam.width, cam.height
        first = pb.RenderChunk(sequence=seq, width=W, height=H, elapsed_ms=ms)
        if out.argmax is not None:
            x, y, v = out.argmax
            first.argmax.CopyFrom(pb.Pixel(x=x, y=y, value=v))
        imgs = {
            k: getattr(out, k) for k in ("relevancy", "rgb", "depth", "alpha") if getattr(out, k) is not None
        }
        if encoding == pb.IMAGE_ENCODING_PNG:
            for k, v in imgs.items():
                setattr(first, f"{k}_png", encode_output_png(k, v.numpy()))
            first.last = True
            yield first
            return
        arrays = {k: v.numpy().astype(np.float32) for k, v in imgs.items()}
        row_bytes = sum(a.itemsize * a[0].size for a in arrays.values()) if arrays else 1
        ranges = row_chunks(H, row_bytes, self.cfg.chunk_bytes)
        for n, (s, e) in enumerate(ranges):
            chunk = first if n == 0 else pb.RenderChunk(sequence=seq)
            chunk.row_start = s
            for k, a in arrays.items():
                getattr(chunk, k).CopyFrom(to_tensor(a[s:e]))
            chunk.last = n == len(ranges) - 1
            yield chunk

    @rpc_stream
    def Render(self, request, context):
        yield from self._render_request(request, context)

    @rpc_stream
    def StreamRender(self, request_iterator, context):
        if not self._streams.acquire(blocking=False):
            raise ResourceExhausted(f"too many pose streams (limit {self.cfg.max_streams})")
        try:
            yield from self._stream(request_iterator, context)
        finally:
            self._streams.release()

    def _stream(self, request_iterator, context):
        """Latest pose wins: a reader thread keeps only the newest request; we render it when free."""
        cond = threading.Condition()
        state = {"latest": None, "done": False, "error": None}

        def read():
            try:
                for req in request_iterator:
                    with cond:
                        state["latest"] = req
                        cond.notify()
            except Exception as e:  # the client went away or sent garbage
                state["error"] = e
            finally:
                with cond:
                    state["done"] = True
                    cond.notify()

        threading.Thread(target=read, daemon=True, name="fmgs-stream-reader").start()
        while context.is_active():
            with cond:
                while state["latest"] is None and not state["done"]:
                    cond.wait(timeout=0.5)
                    if not context.is_active():
                        return
                req, state["latest"] = state["latest"], None
                if req is None and state["done"]:
                    return
            yield from self._render_request(req, context, patient=True)

    # ------------------------------------------------------------------ points and segmentation

    @rpc
    def PointQuery(self, request, context):
        values = convert.texts(request.texts, self.cfg)
        if not request.HasField("points"):
            raise InvalidArgument("points: missing")
        pts = convert.tensor(request.points, "points", (None, 3), self.cfg.max_points)
        engine = self.repo.get(request.scene)
        if engine.field is None:
            raise FailedPrecondition(f"scene {engine.name!r} has no feature field; point queries need one")
        with self._compute(context):
            t0 = time.perf_counter()
            q = self.encoders.embed(engine.encoder_id, values)
            canon = self._canonical(engine, request.canonical_phrases)
            if canon is None:
                canon = self.encoders.embed(engine.encoder_id, list(engine.canonical_phrases))
            a = query_points(engine, pts, q, canon)
        return pb.PointQueryResponse(
            relevancy=to_tensor(a.relevancy.numpy().astype(np.float32)),
            similarity=to_tensor(a.similarity.numpy().astype(np.float32)),
            elapsed_ms=(time.perf_counter() - t0) * 1e3,
        )

    @rpc_stream
    def Segment(self, request, context):
        names = convert.texts(request.class_names, self.cfg, "class_names")
        cam = convert.camera(request.camera, self.cfg) if request.HasField("camera") else None
        if cam is None and not request.per_gaussian:
            raise InvalidArgument(
                "camera/per_gaussian: ask for pixel labels (a camera) or per_gaussian labels"
            )
        engine = self.repo.get(request.scene)
        with self._compute(context):
            t0 = time.perf_counter()
            v = self.encoders.embed(engine.encoder_id, names)
            s = segment(engine, v, cam, request.per_gaussian)
            ms = (time.perf_counter() - t0) * 1e3
        first = pb.SegmentChunk(class_names=names, elapsed_ms=ms)
        parts: list[tuple[str, np.ndarray]] = []
        if s.pixel_labels is not None:
            first.width, first.height = cam.width, cam.height
            parts.append(("pixel_labels", s.pixel_labels.numpy()))
        if s.gaussian_labels is not None:
            parts += [
                ("gaussian_index", s.gaussian_index.numpy()),
                ("gaussian_labels", s.gaussian_labels.numpy()),
            ]
        # The first chunk carries the description; then one chunk per slice of one array.
        chunks = [first]
        for name, a in parts:
            row = a.itemsize * (a[0].size if len(a) else 1)
            for s0, e in row_chunks(len(a), row, self.cfg.chunk_bytes):
                c = pb.SegmentChunk()
                getattr(c, name).CopyFrom(to_tensor(a[s0:e]))
                chunks.append(c)
        chunks[-1].last = True
        yield from chunks
