"""The working-memory budget of requests in flight: each reserves its estimated peak bytes before it
allocates, holds them until its answer has been consumed (a stalled reader keeps holding them), and gets
RESOURCE_EXHAUSTED when they cannot be had within the queue timeout (at once when they exceed the budget).

Estimates are upper bounds per request kind, calibrated by measured peak RSS (benchmarks/reliability.py).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

from fmgs_server.errors import Cancelled, ResourceExhausted
from fmgs_server.slots import POLL_S, gave_up, queue_wait

MiB = 1 << 20

RENDER_BYTES_PER_PIXEL = 64
"""Relevancy render: the rasteriser's float32 channels (1 + 4 canonical) and float64 alpha and depth, the
scored image and the float32 answer and its message copies."""
RGB_BYTES_PER_PIXEL = 96
"""Colour (and depth) render of all Gaussians: float32 RGB, float64 alpha and depth, clamped copies, the
answer and its message copies."""
RENDER_BYTES_PER_GAUSSIAN = 320
"""Per Gaussian of the scene a render projects: the rasteriser's projection arrays (about 125 bytes:
float64 screen positions, depths, conics, int64 boxes), the same again for the visibility pass of a
relevancy render on the compact path, and the exact scores of the Gaussians it touches (float64 dots,
sorted rows and their inverse). Computed from the arrays' sizes, not measured."""
POINT_BYTES_IN_FLIGHT = 48 << 10
"""Per point going through the field at once (hash-grid corners, the heads' activations): measured 25 to
32 KiB with the allocator's overhead (300K points x 2 texts on the demo scene, on two runs)."""
BASE_BYTES = 8 * MiB
"""Any request: decoded request, encoder call, bookkeeping."""


def render_bytes(width: int, height: int, outputs: tuple[str, ...], png: bool, gaussians: int = 0) -> int:
    """Estimated peak working memory of a pose render of a scene of ``gaussians`` Gaussians."""
    px = width * height
    n = px * (RENDER_BYTES_PER_PIXEL if ("relevancy" in outputs or "alpha" in outputs) else 0)
    n += px * (RGB_BYTES_PER_PIXEL if ("rgb" in outputs or "depth" in outputs) else 0)
    if png:
        n += px * 8 * len(outputs)  # uint8/uint16 buffers and the encoded bytes
    return BASE_BYTES + n + gaussians * RENDER_BYTES_PER_GAUSSIAN


def point_bytes(points: int, texts: int, chunk: int) -> int:
    """Estimated peak working memory of a point query: one chunk through the field, the points as received
    and widened (64 bytes each), and [T,P] float32 relevancy and similarity held in five forms at once at
    worst (tensors, arrays, wire bytes, serialised message, margin): 48 bytes per (text, point). Measured
    438-498 MiB for 1M points x 8 texts (RELIABILITY.md), 251-311 MiB for 300K x 2 (tests)."""
    return BASE_BYTES + min(points, chunk) * POINT_BYTES_IN_FLIGHT + points * 64 + texts * points * 48


def text_bytes(top_k: int, texts: int, columns: int, embedded: int = 0, dim: int = 0) -> int:
    """Estimated peak working memory of a text query: an upper bound per embedded Gaussian and text
    (float32), one text's refinement pass over at most every embedded Gaussian (rows, float32 dots and
    magnitudes, float64 bounds: 64 bytes each), a rescoring chunk (RESCORE_CHUNK rows); per
    answer row the index, scores and asked columns (about 4 bytes each), answers held for every text,
    and their message copies."""
    from fmgs.query.tuning import RESCORE_CHUNK

    scan = embedded * (4 * texts + 64) + RESCORE_CHUNK * dim * 12
    return BASE_BYTES + scan + 2 * texts * top_k * (16 + 4 * columns)


def segment_bytes(width: int, height: int, classes: int, gaussians: int) -> int:
    """Estimated peak working memory of a segmentation: rendered class dots and labels, per-Gaussian
    labels."""
    return BASE_BYTES + width * height * (classes * 8 + 24) + gaussians * (classes * 4 + 16)


def geometry_bytes(gaussians: int, k: int) -> int:
    """Estimated peak working memory of a geometry call: the opacity test over the scene's Gaussians
    (float64, float32, mask), the sample's indices, its columns (48 bytes a row) and their message
    copies."""
    return BASE_BYTES + gaussians * 21 + k * (8 + 2 * 48)


class WorkBudget:
    """Bytes of working memory shared by the requests in flight (``total`` 0: unlimited)."""

    def __init__(self, total: int, queue_timeout_s: float) -> None:
        self.total = total
        self.queue_timeout_s = queue_timeout_s
        self._used = 0
        self._cond = threading.Condition()

    @property
    def used(self) -> int:
        return self._used

    @contextmanager
    def reserve(self, nbytes: int, context, what: str, patient: bool = False) -> Iterator[None]:
        """Hold ``nbytes`` for the duration; waits for room at most queue_timeout_s (never past the
        deadline, and no longer than the client is there: CANCELLED), or, ``patient`` (pose streams), as
        long as the client is there."""
        if not self.total:
            yield
            return
        if nbytes > self.total:
            raise ResourceExhausted(
                f"{what} needs about {nbytes / MiB:.0f} MiB of working memory, more than the server's "
                f"work_memory_bytes ({self.total / MiB:.0f} MiB); ask for less"
            )
        end = time.monotonic() + (0.0 if patient else queue_wait(context, self.queue_timeout_s))
        with self._cond:
            while self._used + nbytes > self.total:
                if patient:
                    if not context.is_active():
                        raise ResourceExhausted("the client went away while waiting for working memory")
                    self._cond.wait(POLL_S)
                    continue
                remaining = end - time.monotonic()
                if remaining <= 0:
                    raise gave_up(
                        context,
                        "working memory",
                        f"server busy: {what} needs about {nbytes / MiB:.0f} MiB of working memory and "
                        f"{(self.total - self._used) / MiB:.0f} MiB are free; retry later",
                    )
                if not context.is_active():
                    raise Cancelled("the client went away while waiting for working memory")
                self._cond.wait(min(remaining, POLL_S))
            self._used += nbytes
        try:
            yield
        finally:
            with self._cond:
                self._used -= nbytes
                self._cond.notify_all()

    @contextmanager
    def reserve_until_sent(self, nbytes: int, context, what: str) -> Iterator[None]:
        """As ``reserve``, for a unary answer, which grpc serialises and sends after the handler has
        returned: held until both the ``with`` block is left and the call has ended (the context's
        ``add_callback``; a context without one, such as a forwarded call's, releases at the block's end)."""
        held = self.reserve(nbytes, context, what)
        held.__enter__()
        left, lock = [2], threading.Lock()

        def end() -> None:
            with lock:
                left[0] -= 1
                last = left[0] == 0
            if last:
                held.__exit__(None, None, None)

        add = getattr(context, "add_callback", None)
        if add is None or not add(end):  # no callbacks, or the call has ended already
            end()
        try:
            yield
        finally:
            end()
