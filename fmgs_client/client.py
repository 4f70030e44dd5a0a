"""``FmgsClient``: the gRPC client of the FMGS query service (grpcio + health stubs, protobuf, numpy).

Streamed answers are reassembled by plain functions (``assemble_text_answers``, ``assemble_render``,
``assemble_render_stream``, ``assemble_segment``) that take an iterable of wire chunks, so they can be
tested with hand-built messages and reused by other transports.
"""

from __future__ import annotations

import random
import threading
import time
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import grpc
import grpc.experimental
import numpy as np
from grpc_health.v1 import health_pb2, health_pb2_grpc

from fmgs_client.retry import RetryPolicy, channel_options
from fmgs_client.types import (
    CameraSpec,
    Geometry,
    Instance,
    Pixel,
    PointResult,
    Presence,
    RenderResult,
    SceneInfo,
    SegmentResult,
    TextAnswer,
    require_finite,
)
from fmgs_wire import DEFAULT_PORT
from fmgs_wire.images import PNG_SCALE, decode_png
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc
from fmgs_wire.tensors import TensorError, from_tensor, join, to_tensor

DEFAULT_ADDRESS = f"127.0.0.1:{DEFAULT_PORT}"
MiB = 1 << 20

# Per-Gaussian fields of a text answer: name -> (wire enum, trailing shape, dtype).
GAUSSIAN_FIELDS: dict[str, tuple[int, tuple[int, ...], type]] = {
    "similarity": (pb.GAUSSIAN_FIELD_SIMILARITY, (), np.float32),
    "mean": (pb.GAUSSIAN_FIELD_MEAN, (3,), np.float32),
    "opacity": (pb.GAUSSIAN_FIELD_OPACITY, (), np.float32),
    "scale": (pb.GAUSSIAN_FIELD_SCALE, (3,), np.float32),
    "rotation": (pb.GAUSSIAN_FIELD_ROTATION, (4,), np.float32),
    "color": (pb.GAUSSIAN_FIELD_COLOR, (3,), np.float32),
    "instance": (pb.GAUSSIAN_FIELD_INSTANCE, (), np.int32),
}
_TEXT_ROWS: dict[str, tuple[tuple[int, ...], type]] = {
    "index": ((), np.int64),
    "relevancy": ((), np.float32),
    **{k: (v[1], v[2]) for k, v in GAUSSIAN_FIELDS.items()},
}
RENDER_OUTPUTS = {
    "relevancy": pb.RENDER_OUTPUT_RELEVANCY,
    "rgb": pb.RENDER_OUTPUT_RGB,
    "depth": pb.RENDER_OUTPUT_DEPTH,
    "alpha": pb.RENDER_OUTPUT_ALPHA,
}
ENCODINGS = {"float32": pb.IMAGE_ENCODING_FLOAT32, "png": pb.IMAGE_ENCODING_PNG}
# Trailing shape of each rendered image after [H,W].
_IMAGE_TAIL = {"relevancy": (), "rgb": (3,), "depth": (), "alpha": ()}
# PNG encoding (see the proto): 8-bit value*255, depth 16-bit millimetres.
_PNG_SCALE = PNG_SCALE

T = TypeVar("T")


class FmgsError(RuntimeError):
    """A failed call: ``code`` is the gRPC status name (e.g. ``"NOT_FOUND"``), ``details`` the message.

    Malformed answers (bad tensors, NaN or infinite numbers, chunks out of order, render outputs asked for
    but left out) are reported with code ``"DATA_LOSS"``.
    """

    def __init__(self, code: str, details: str) -> None:
        self.code = code
        self.details = details
        super().__init__(f"{code}: {details}")


class ChunkError(ValueError):
    """Streamed chunks that do not fit together (out of order, missing, inconsistent sizes)."""


# ---------------------------------------------------------------- reassembly (plain functions)


def _rows(t: pb.Tensor, name: str, tail: tuple[int, ...], dtype: type) -> np.ndarray:
    a = from_tensor(t, name)
    if a.ndim != 1 + len(tail) or a.shape[1:] != tail:
        raise TensorError(name, f"expected shape [k{''.join(f',{d}' for d in tail)}], got {list(a.shape)}")
    return a.astype(dtype, copy=False)


def _ms(value: float, what: str) -> float:
    """A server time in milliseconds; ValueError naming ``what`` when it is NaN or infinite."""
    return float(require_finite(np.float64(value), f"{what}.elapsed_ms"))


@dataclass
class _TextState:
    first: pb.TextQueryChunk
    rows: int = 0
    parts: dict[str, list[np.ndarray]] = field(default_factory=dict)


def assemble_text_answers(
    chunks: Iterable[pb.TextQueryChunk], texts: Sequence[str], fields: Collection[str] = ()
) -> list[TextAnswer]:
    """Reassemble the chunks of a text query (texts may interleave) into one answer per text, in order.

    ``fields`` are the per-Gaussian fields that were asked for: those always come back as arrays (empty
    ones when no rows came); fields the server sent unasked come back too, the rest are None.
    Raises TensorError (naming the field) or ChunkError when the chunks do not fit together.
    """
    state: dict[int, _TextState] = {}
    for c in chunks:
        i = int(c.text_index)
        if i >= len(texts):
            raise ChunkError(f"text_index {i} out of range for {len(texts)} texts")
        st = state.get(i)
        if st is None:
            st = state[i] = _TextState(first=c)
        present = [n for n in _TEXT_ROWS if c.HasField(n)]
        arrays = {n: _rows(getattr(c, n), f"text[{i}].{n}", *_TEXT_ROWS[n]) for n in present}
        k = len(arrays["index"]) if "index" in arrays else 0
        for n, a in arrays.items():
            if len(a) != k:
                raise ChunkError(f"text[{i}].{n}: {len(a)} rows in a chunk of {k} indices")
        if k and int(c.start) != st.rows:
            raise ChunkError(f"text[{i}]: chunk starts at row {c.start}, expected {st.rows}")
        st.rows += k
        for n, a in arrays.items():
            st.parts.setdefault(n, []).append(a)
    answers = []
    for i, text in enumerate(texts):
        st = state.get(i)
        if st is None:
            raise ChunkError(f"no answer for text[{i}] {text!r}")
        if st.rows != st.first.total:
            raise ChunkError(f"text[{i}]: got {st.rows} rows, the first chunk announced {st.first.total}")

        def get(n: str, st: _TextState = st, i: int = i) -> np.ndarray:
            tail, dtype = _TEXT_ROWS[n]
            return require_finite(join(st.parts.get(n, []), (0, *tail), dtype), f"text[{i}].{n}")

        index, relevancy = get("index"), get("relevancy")
        extra = {n: get(n) if (n in fields or n in st.parts) else None for n in GAUSSIAN_FIELDS}
        for n, arr in [("relevancy", relevancy), *extra.items()]:
            if arr is not None and len(arr) != st.rows:
                raise ChunkError(f"text[{i}].{n}: {len(arr)} rows for {st.rows} indices")
        try:
            instances = tuple(Instance.from_proto(m) for m in st.first.instances)
            presence = Presence.from_proto(st.first.presence) if st.first.HasField("presence") else None
        except ValueError as e:
            raise ChunkError(f"text[{i}]: {e}") from None
        answers.append(
            TextAnswer(
                text=st.first.text or text,
                index=index,
                relevancy=relevancy,
                **extra,
                instances=instances,
                elapsed_ms=_ms(st.first.elapsed_ms, f"text[{i}]"),
                rescored=int(st.first.rescored),
                presence=presence,
            )
        )
    return answers


@dataclass
class _RenderState:
    first: pb.RenderChunk
    rows: int = 0
    parts: dict[str, list[np.ndarray]] = field(default_factory=dict)


def _render_add(st: _RenderState, c: pb.RenderChunk) -> None:
    w = int(st.first.width)
    present = [n for n in _IMAGE_TAIL if c.HasField(n)]
    arrays = {n: from_tensor(getattr(c, n), f"render[{c.sequence}].{n}") for n in present}
    k = None
    for n, a in arrays.items():
        want = (a.shape[0] if a.ndim else -1, w, *_IMAGE_TAIL[n])
        if a.shape != want:
            raise TensorError(f"render[{c.sequence}].{n}", f"expected shape [h,{w},...], got {list(a.shape)}")
        if k is not None and len(a) != k:
            raise ChunkError(f"render[{c.sequence}].{n}: {len(a)} rows where other images have {k}")
        k = len(a)
    if k and int(c.row_start) != st.rows:
        raise ChunkError(f"render[{c.sequence}]: chunk starts at row {c.row_start}, expected {st.rows}")
    st.rows += k or 0
    for n, a in arrays.items():
        st.parts.setdefault(n, []).append(a)


def _render_finish(st: _RenderState) -> RenderResult:
    f = st.first
    seq, h, w = int(f.sequence), int(f.height), int(f.width)
    images: dict[str, np.ndarray | None] = dict.fromkeys(_IMAGE_TAIL)
    for n, parts in st.parts.items():
        a = join(parts)
        if a.shape[0] != h:
            raise ChunkError(f"render[{seq}].{n}: got {a.shape[0]} rows of {h}")
        images[n] = require_finite(a, f"render[{seq}].{n}").astype(np.float32, copy=False)
    png = {n: getattr(f, f"{n}_png") for n in _IMAGE_TAIL if getattr(f, f"{n}_png")}
    for n, data in png.items():
        if images[n] is None:
            try:
                img = decode_png(data)
            except Exception as e:  # zlib/struct errors as well as ValueError: all mean a bad PNG
                raise ChunkError(f"render[{seq}].{n}_png: {e}") from None
            if img.shape != (h, w, *_IMAGE_TAIL[n]):
                raise ChunkError(f"render[{seq}].{n}_png: image {img.shape} for a {w}x{h} render")
            images[n] = (img / np.float32(_PNG_SCALE[n])).astype(np.float32)
    argmax = None
    if f.HasField("argmax"):
        value = float(require_finite(np.float64(f.argmax.value), f"render[{seq}].argmax"))
        argmax = Pixel(int(f.argmax.x), int(f.argmax.y), value)
    return RenderResult(
        sequence=seq,
        width=w,
        height=h,
        relevancy=images["relevancy"],
        rgb=images["rgb"],
        depth=images["depth"],
        alpha=images["alpha"],
        argmax=argmax,
        png=png,
        elapsed_ms=_ms(f.elapsed_ms, f"render[{seq}]"),
    )


def assemble_render_stream(
    chunks: Iterable[pb.RenderChunk], require_last: bool = True
) -> Iterator[RenderResult]:
    """Yield one RenderResult per answer, when its ``last`` chunk arrives (answers keyed by sequence).

    With ``require_last`` False, answers still open when the stream ends are finished as they are
    (unary calls whose server leaves ``last`` unset).
    """
    open_: dict[int, _RenderState] = {}
    for c in chunks:
        seq = int(c.sequence)
        st = open_.get(seq)
        if st is None:
            st = open_[seq] = _RenderState(first=c)
        _render_add(st, c)
        if c.last:
            yield _render_finish(open_.pop(seq))
    if open_ and require_last:
        raise ChunkError(f"stream ended before the last chunk of sequence {sorted(open_)}")
    for seq in sorted(open_):
        yield _render_finish(open_[seq])


def _asked_for(results: Iterable[RenderResult], outputs: Sequence[str]) -> Iterator[RenderResult]:
    """The results, each checked to hold every output asked for (ChunkError naming those left out)."""
    for r in results:
        missing = [n for n in outputs if getattr(r, n) is None]
        if missing:
            raise ChunkError(f"render[{r.sequence}]: no {', '.join(missing)} although asked for")
        yield r


def assemble_render(chunks: Iterable[pb.RenderChunk]) -> RenderResult:
    """The single answer of a ``Render`` call."""
    results = list(assemble_render_stream(chunks, require_last=False))
    if len(results) != 1:
        raise ChunkError(f"expected one rendered view, got {len(results)}")
    return results[0]


def assemble_segment(chunks: Iterable[pb.SegmentChunk]) -> SegmentResult:
    """Reassemble the chunks of a ``Segment`` call (ends at ``last`` or at the end of the stream).

    Each array is concatenated over the chunks that carry it (the server may send them one after the
    other, not row-aligned); the index and label arrays must end up the same length.
    """
    first: pb.SegmentChunk | None = None
    parts: dict[str, list[np.ndarray]] = {"pixel_labels": [], "gaussian_index": [], "gaussian_labels": []}
    dtypes = {"pixel_labels": np.int32, "gaussian_index": np.int64, "gaussian_labels": np.int32}
    for c in chunks:
        if first is None:
            first = c
        w = int(first.width)
        for n, dt in dtypes.items():
            if c.HasField(n):
                tail = (w,) if n == "pixel_labels" else ()
                parts[n].append(_rows(getattr(c, n), f"segment.{n}", tail, dt))
        if c.last:
            break
    if first is None:
        raise ChunkError("segment: empty answer")
    h, w = int(first.height), int(first.width)
    labels = None
    if parts["pixel_labels"] or h or w:
        labels = join(parts["pixel_labels"], (0, w), np.int32)
        if labels.shape != (h, w):
            raise ChunkError(f"segment.pixel_labels: got {list(labels.shape)}, expected [{h},{w}]")
    gidx = join(parts["gaussian_index"], (0,), np.int64) if parts["gaussian_index"] else None
    glab = join(parts["gaussian_labels"], (0,), np.int32) if parts["gaussian_labels"] else None
    if (gidx is None) != (glab is None) or (gidx is not None and len(gidx) != len(glab)):
        n_i, n_l = (None if a is None else len(a) for a in (gidx, glab))
        raise ChunkError(f"segment: {n_i} Gaussian indices but {n_l} labels")
    return SegmentResult(
        class_names=tuple(first.class_names),
        pixel_labels=labels,
        gaussian_index=gidx,
        gaussian_labels=glab,
        elapsed_ms=_ms(first.elapsed_ms, "segment"),
    )


GEOMETRY_ROWS: dict[str, tuple[tuple[int, ...], type]] = {
    "index": ((), np.int64),
    "mean": ((3,), np.float32),
    "color": ((3,), np.float32),
    "opacity": ((), np.float32),
    "scale": ((3,), np.float32),
}


def assemble_geometry(chunks: Iterable[pb.GeometryChunk], max_rows: int | None = None) -> Geometry:
    """Reassemble the chunks of a ``Geometry`` call into preallocated arrays (ends at ``last`` or at the
    end of the stream). ``max_rows``: refuse an answer announcing more rows (the caller's cap), before
    allocating. Raises TensorError or ChunkError when the chunks do not fit together."""
    first: pb.GeometryChunk | None = None
    out: dict[str, np.ndarray] = {}
    rows = 0
    for c in chunks:
        if first is None:
            first = c
            total = int(c.total)
            if max_rows is not None and total > max_rows:
                raise ChunkError(f"geometry: {total} rows announced, {max_rows} asked for at most")
            out = {n: np.empty((total, *tail), dt) for n, (tail, dt) in GEOMETRY_ROWS.items()}
        arrays = {n: _rows(getattr(c, n), f"geometry.{n}", *GEOMETRY_ROWS[n]) for n in GEOMETRY_ROWS}
        k = len(arrays["index"])
        if any(len(a) != k for a in arrays.values()):
            raise ChunkError(f"geometry: columns of unequal length in the chunk at row {c.start}")
        if int(c.start) != rows or rows + k > len(out["index"]):
            raise ChunkError(
                f"geometry: chunk of {k} rows at {c.start}, expected row {rows} of {len(out['index'])}"
            )
        for n, a in arrays.items():
            out[n][rows : rows + k] = a
        rows += k
        if c.last:
            break
    if first is None:
        raise ChunkError("geometry: empty answer")
    if rows != len(out["index"]):
        raise ChunkError(f"geometry: got {rows} rows, the first chunk announced {len(out['index'])}")
    if len(first.bounds) != 6:
        raise ChunkError(f"geometry: bounds has {len(first.bounds)} numbers, expected 6")
    for n, a in out.items():
        require_finite(a, f"geometry.{n}")
    return Geometry(
        **out,
        num_gaussians=int(first.num_gaussians),
        qualified=int(first.qualified),
        bounds=require_finite(np.asarray(first.bounds, np.float64), "geometry.bounds"),
        elapsed_ms=_ms(first.elapsed_ms, "geometry"),
    )


def point_result(resp: pb.PointQueryResponse, n_texts: int, n_points: int) -> PointResult:
    """Decode a ``PointQueryResponse`` and check both arrays are [T,P]."""
    out = {}
    for n in ("relevancy", "similarity"):
        a = from_tensor(getattr(resp, n), f"points.{n}")
        if a.shape != (n_texts, n_points):
            raise TensorError(f"points.{n}", f"expected shape [{n_texts},{n_points}], got {list(a.shape)}")
        out[n] = require_finite(a, f"points.{n}").astype(np.float32, copy=False)
    return PointResult(out["relevancy"], out["similarity"], _ms(resp.elapsed_ms, "points"))


# ---------------------------------------------------------------- grpc.health.v1


def health_status_name(status: int) -> str:
    """Name of a ``HealthCheckResponse.ServingStatus`` value (``"SERVING"``, ...; ``"UNKNOWN(7)"`` if new)."""
    try:
        return health_pb2.HealthCheckResponse.ServingStatus.Name(status)
    except ValueError:
        return f"UNKNOWN({status})"


# ---------------------------------------------------------------- the client


def _pem(x: str | bytes | Path | None) -> bytes | None:
    """PEM bytes from bytes, PEM text, or a file path."""
    if x is None or isinstance(x, bytes):
        return x
    if isinstance(x, str) and x.lstrip().startswith("-----BEGIN"):
        return x.encode()
    return Path(x).read_bytes()


def _texts(texts: str | Sequence[str]) -> list[str]:
    out = [texts] if isinstance(texts, str) else list(texts)
    if not out or not all(isinstance(t, str) for t in out):
        raise ValueError("texts: need one or more strings")
    return out


def _enum(table: Mapping[str, int], names: Iterable[str], what: str) -> list[int]:
    out = []
    for n in names:
        if n not in table:
            raise ValueError(f"{what}: unknown {n!r} (choose from {', '.join(table)})")
        out.append(table[n])
    return out


class FmgsClient:
    """Client of one FMGS server.

    ``address`` is ``host:port``. Without ``root_cert`` the channel is plaintext; with it, TLS (mutual
    TLS when ``client_cert`` and ``client_key`` are given too; each is PEM bytes, PEM text or a path).
    ``token`` is sent as ``authorization: Bearer <token>`` on every call. ``timeout`` is the deadline
    of each call in seconds (None: none; pose streams have none unless given). ``retry``: how reads
    failing with UNAVAILABLE are tried again and how fast a restarted server is found (gRPC's own retry
    policy and reconnect back-off, fmgs_client.retry). Failed calls raise :class:`FmgsError`. Use as a
    context manager or call :meth:`close`.
    """

    def __init__(
        self,
        address: str = DEFAULT_ADDRESS,
        token: str | None = None,
        root_cert: str | bytes | Path | None = None,
        client_cert: str | bytes | Path | None = None,
        client_key: str | bytes | Path | None = None,
        timeout: float | None = 30.0,
        max_message_bytes: int = 64 * MiB,
        retry: RetryPolicy | None = None,
    ) -> None:
        if (client_cert is None) != (client_key is None):
            raise ValueError("client_cert and client_key go together")
        if client_cert is not None and root_cert is None:
            raise ValueError("a client certificate needs TLS: give root_cert too")
        self.address = address
        self.timeout = timeout
        self._retry = retry or RetryPolicy()
        options = [
            ("grpc.max_receive_message_length", max_message_bytes),
            ("grpc.max_send_message_length", max_message_bytes),
            # Server-streaming calls (Render, TextQuery, ...) run on the calling thread instead of a thread
            # spawned per call (the saving per call: GPU.md, the pose part's gRPC breakdown).
            (grpc.experimental.ChannelOptions.SingleThreadedUnaryStream, 1),
            *channel_options(self._retry),
        ]
        if root_cert is None:
            self._channel = grpc.insecure_channel(address, options=options)
        else:
            creds = grpc.ssl_channel_credentials(
                root_certificates=_pem(root_cert),
                private_key=_pem(client_key),
                certificate_chain=_pem(client_cert),
            )
            self._channel = grpc.secure_channel(address, creds, options=options)
        self._metadata: tuple[tuple[str, str], ...] = (("authorization", f"Bearer {token}"),) if token else ()
        self._stub = pb_grpc.FmgsStub(self._channel)
        self._health = health_pb2_grpc.HealthStub(self._channel)

    # -- plumbing

    def close(self) -> None:
        """Close the channel (idempotent)."""
        self._channel.close()

    def __enter__(self) -> FmgsClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _unary(self, method: Callable[..., T], request: Any) -> T:
        try:
            return method(request, metadata=self._metadata, timeout=self.timeout)
        except grpc.RpcError as e:
            raise _error(e) from None

    def _stream(self, call: Any) -> Iterator[Any]:
        """Iterate a response stream, turning gRPC failures into FmgsError."""
        try:
            yield from call
        except grpc.RpcError as e:
            raise _error(e) from None

    def _read_stream(self, start: Callable[[float | None], Any]) -> Iterator[Any]:
        """The messages of a read's response stream, ``start(timeout)`` tried again while it fails with
        UNAVAILABLE before its first message, with the retry policy's back-off, within one deadline.

        This is what gRPC's retry policy does for unary reads; streams are retried here because grpcio's
        own stream retries (1.85) can leave a call waiting past its deadline once the server's
        connection drops (tests/client/test_retry.py)."""
        policy = self._retry
        deadline = None if self.timeout is None else time.monotonic() + self.timeout
        backoff = policy.initial_backoff_s
        for attempt in range(1, policy.attempts + 1):
            left = None if deadline is None else max(deadline - time.monotonic(), 1e-3)
            got = False
            try:
                for m in start(left):
                    got = True
                    yield m
                return
            except grpc.RpcError as e:
                pause = random.uniform(0.0, backoff)  # gRPC's own jitter: uniform up to the back-off
                late = deadline is not None and time.monotonic() + pause >= deadline
                if got or e.code() != grpc.StatusCode.UNAVAILABLE or attempt == policy.attempts or late:
                    raise _error(e) from None
            time.sleep(pause)
            backoff = min(backoff * policy.backoff_multiplier, policy.max_backoff_s)

    def _decode(self, fn: Callable[[], T]) -> T:
        try:
            return fn()
        except (TensorError, ChunkError, ValueError) as e:
            raise FmgsError("DATA_LOSS", f"malformed answer: {e}") from e

    # -- scenes

    def list_scenes(self) -> list[SceneInfo]:
        """Every scene in the server's repository, loaded or not."""
        resp = self._unary(self._stub.ListScenes, pb.ListScenesRequest())
        return self._decode(lambda: [SceneInfo.from_proto(s) for s in resp.scenes])

    def scene(self, name: str) -> SceneInfo:
        """One scene's metadata (NOT_FOUND for an unknown name)."""
        resp = self._unary(self._stub.GetScene, pb.SceneRequest(scene=name))
        return self._decode(lambda: SceneInfo.from_proto(resp))

    def load(self, scene: str) -> SceneInfo:
        """Load a scene into memory (admin)."""
        resp = self._unary(self._stub.LoadScene, pb.SceneRequest(scene=scene))
        return self._decode(lambda: SceneInfo.from_proto(resp))

    def unload(self, scene: str) -> SceneInfo:
        """Drop a scene from memory (admin)."""
        resp = self._unary(self._stub.UnloadScene, pb.SceneRequest(scene=scene))
        return self._decode(lambda: SceneInfo.from_proto(resp))

    def reload(self, scene: str) -> SceneInfo:
        """Reload a scene from its files (admin)."""
        resp = self._unary(self._stub.ReloadScene, pb.SceneRequest(scene=scene))
        return self._decode(lambda: SceneInfo.from_proto(resp))

    def health(self, service: str = "") -> str:
        """Standard gRPC health check: ``SERVING``, ``NOT_SERVING``, ``SERVICE_UNKNOWN`` or ``UNKNOWN``.

        A server without the health service raises FmgsError("UNIMPLEMENTED", ...).
        """
        req = health_pb2.HealthCheckRequest(service=service)
        try:
            return health_status_name(self._unary(self._health.Check, req).status)
        except FmgsError as e:
            if e.code == "INTERNAL" and "deserializ" in e.details.lower():
                raise FmgsError("DATA_LOSS", f"malformed health answer: {e.details}") from None
            raise

    # -- queries

    def query(
        self,
        scene: str,
        texts: str | Sequence[str],
        top_k: int = 100,
        threshold: float = 0.0,
        fields: Iterable[str] = (),
        instances: bool | Mapping[str, float | int] = False,
        canonical_phrases: Sequence[str] | None = None,
        embeddings: np.ndarray | None = None,
        encoder_id: str = "",
    ) -> list[TextAnswer]:
        """Rank the scene's Gaussians by relevancy to each text; one :class:`TextAnswer` per text.

        ``fields``: extra per-Gaussian arrays, any of ``similarity mean opacity scale rotation color
        instance``. ``instances``: True, or a dict with ``eps``, ``min_points``, ``max_instances``, to
        group the relevant Gaussians into objects (``instance`` is then added to ``fields``).
        ``embeddings`` [T,D] float32 from ``encoder_id`` replace encoding the texts on the server.
        """
        texts = _texts(texts)
        fields = list(dict.fromkeys(fields))
        enums = _enum({k: v[0] for k, v in GAUSSIAN_FIELDS.items()}, fields, "fields")
        inst = pb.InstanceOptions()
        if instances:
            opts = dict(instances) if isinstance(instances, Mapping) else {}
            unknown = set(opts) - {"eps", "min_points", "max_instances"}
            if unknown:
                raise ValueError(f"instances: unknown options {sorted(unknown)}")
            inst = pb.InstanceOptions(
                enabled=True,
                eps=float(opts.get("eps", 0.0)),
                min_points=int(opts.get("min_points", 0)),
                max_instances=int(opts.get("max_instances", 0)),
            )
            if "instance" not in fields:
                fields.append("instance")
                enums.append(pb.GAUSSIAN_FIELD_INSTANCE)
        if top_k < 0 or threshold < 0:
            raise ValueError("top_k and threshold must be >= 0")
        req = pb.TextQueryRequest(
            scene=scene,
            texts=texts,
            top_k=int(top_k),
            threshold=float(threshold),
            fields=enums,
            instances=inst,
            canonical_phrases=list(canonical_phrases or ()),
            encoder_id=encoder_id,
        )
        if embeddings is not None:
            emb = np.asarray(embeddings, np.float32)
            if emb.ndim != 2 or len(emb) != len(texts):
                raise ValueError(f"embeddings: expected [{len(texts)},D], got {emb.shape}")
            req.embeddings.CopyFrom(to_tensor(emb))
        chunks = self._read_stream(lambda t: self._stub.TextQuery(req, metadata=self._metadata, timeout=t))
        return self._decode(lambda: assemble_text_answers(chunks, texts, fields))

    def _render_request(
        self,
        scene: str,
        camera: CameraSpec,
        text: str,
        outputs: Iterable[str],
        encoding: str,
        canonical_phrases: Sequence[str] | None,
        sequence: int = 0,
    ) -> pb.RenderRequest:
        if not isinstance(camera, CameraSpec):
            raise TypeError(f"camera: expected a CameraSpec, got {type(camera).__name__}")
        if encoding not in ENCODINGS:
            raise ValueError(f"encoding: unknown {encoding!r} (choose from {', '.join(ENCODINGS)})")
        return pb.RenderRequest(
            scene=scene,
            camera=camera.to_proto(),
            text=text,
            outputs=_enum(RENDER_OUTPUTS, outputs, "outputs"),
            encoding=ENCODINGS[encoding],
            canonical_phrases=list(canonical_phrases or ()),
            sequence=sequence,
        )

    def render(
        self,
        scene: str,
        camera: CameraSpec,
        text: str = "",
        outputs: Iterable[str] = ("relevancy",),
        encoding: str = "float32",
        canonical_phrases: Sequence[str] | None = None,
    ) -> RenderResult:
        """Render one view: ``outputs`` among ``relevancy rgb depth alpha`` (relevancy needs ``text``).

        ``encoding="png"`` asks for PNG bytes (smaller on the wire); they are decoded into the same
        arrays, quantised (8-bit, depth in millimetres), and kept in ``RenderResult.png``.
        """
        outputs = tuple(outputs)
        req = self._render_request(scene, camera, text, outputs, encoding, canonical_phrases)
        chunks = self._read_stream(lambda t: self._stub.Render(req, metadata=self._metadata, timeout=t))
        return self._decode(lambda: next(_asked_for([assemble_render(chunks)], outputs)))

    def stream(
        self,
        scene: str,
        cameras: Iterable[CameraSpec],
        text: str = "",
        outputs: Iterable[str] = ("relevancy",),
        encoding: str = "float32",
        canonical_phrases: Sequence[str] | None = None,
        timeout: float | None = None,
    ) -> Iterator[RenderResult]:
        """Render a stream of poses (bidirectional ``StreamRender``), yielding views as they come.

        Camera i is sent with sequence number i, echoed in ``RenderResult.sequence``. The server
        renders the newest pose whenever it is free, so a slow consumer gets fewer views than poses.
        ``cameras`` may be a generator producing poses live; it is consumed on a gRPC thread. Leaving
        the loop early cancels the call. ``timeout`` bounds the whole stream (default: no deadline).
        """
        outputs = tuple(outputs)
        failed: list[BaseException] = []
        lock = threading.Lock()

        def requests() -> Iterator[pb.RenderRequest]:
            # An exception raised here would be swallowed by gRPC (it only cancels the call): keep it
            # and end the request stream, then raise it on the consumer's side.
            try:
                for seq, cam in enumerate(cameras):
                    yield self._render_request(scene, cam, text, outputs, encoding, canonical_phrases, seq)
            except Exception as e:
                with lock:
                    failed.append(e)

        call = self._stub.StreamRender(requests(), metadata=self._metadata, timeout=timeout)
        try:
            it = _asked_for(assemble_render_stream(self._stream(call)), outputs)
            while True:
                try:
                    res = self._decode(lambda: next(it, None))
                except FmgsError:
                    if failed:
                        raise failed[0] from None
                    raise
                if failed:
                    raise failed[0]
                if res is None:
                    return
                yield res
        finally:
            call.cancel()

    def points(
        self,
        scene: str,
        texts: str | Sequence[str],
        points: np.ndarray,
        canonical_phrases: Sequence[str] | None = None,
    ) -> PointResult:
        """Relevancy and similarity [T,P] of world points [P,3] through the scene's feature field."""
        texts = _texts(texts)
        pts = np.asarray(points)
        if pts.dtype != np.float32:
            pts = pts.astype(np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points: expected [P,3], got {pts.shape}")
        req = pb.PointQueryRequest(
            scene=scene, texts=texts, points=to_tensor(pts), canonical_phrases=list(canonical_phrases or ())
        )
        resp = self._unary(self._stub.PointQuery, req)
        return self._decode(lambda: point_result(resp, len(texts), len(pts)))

    def segment(
        self,
        scene: str,
        class_names: Sequence[str],
        camera: CameraSpec | None = None,
        per_gaussian: bool = True,
    ) -> SegmentResult:
        """Label the scene's Gaussians (and, given a camera, its pixels) with the best class name."""
        names = _texts(class_names)
        req = pb.SegmentRequest(scene=scene, class_names=names, per_gaussian=per_gaussian)
        if camera is not None:
            req.camera.CopyFrom(camera.to_proto())
        chunks = self._read_stream(lambda t: self._stub.Segment(req, metadata=self._metadata, timeout=t))
        return self._decode(lambda: assemble_segment(chunks))

    def geometry(self, scene: str, max_gaussians: int = 0, min_opacity: float = 0.0) -> Geometry:
        """The scene's Gaussians as points: at most ``max_gaussians`` (0: the server's default) of those
        with opacity >= ``min_opacity``, a uniform sample (fixed seed) when more qualify."""
        if max_gaussians < 0 or not 0.0 <= min_opacity < 1.0:
            raise ValueError("max_gaussians must be >= 0 and min_opacity in [0, 1)")
        req = pb.GeometryRequest(scene=scene, max_gaussians=max_gaussians, min_opacity=min_opacity)
        chunks = self._read_stream(lambda t: self._stub.Geometry(req, metadata=self._metadata, timeout=t))
        return self._decode(lambda: assemble_geometry(chunks, max_gaussians or None))


def _error(e: grpc.RpcError) -> FmgsError:
    """FmgsError from a gRPC failure (the status code's name and its details)."""
    code = e.code() if hasattr(e, "code") else None
    details = e.details() if hasattr(e, "details") else str(e)
    return FmgsError(code.name if code is not None else "UNKNOWN", details or "")
