"""Compute slots and stream slots: how many requests work at once, and how long a request waits for one."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

from fmgs_server.errors import Cancelled, DeadlineExceeded, ResourceExhausted, ServiceError

POLL_S = 0.25
"""How often a request waiting for a slot or memory checks that its client is still there."""


def queue_wait(context, queue_timeout_s: float) -> float:
    """How long a request may wait for a slot or memory: queue_timeout_s, never past its deadline
    (DEADLINE_EXCEEDED at once when that has passed)."""
    left = context.time_remaining()
    if left is None:
        return queue_timeout_s
    if left <= 0:
        raise DeadlineExceeded("the deadline passed before the work could start")
    return min(queue_timeout_s, left)


def gave_up(context, what: str, busy: str) -> ServiceError:
    """The error for a wait that timed out: its deadline passed, or the server is busy."""
    left = context.time_remaining()
    if left is not None and left <= 0:
        return DeadlineExceeded(f"the deadline passed while waiting for {what}")
    return ResourceExhausted(busy)


class Slots:
    """``compute`` slots (renders, ranking, loading) and ``streams`` (open StreamRender calls)."""

    def __init__(self, compute: int, streams: int, queue_timeout_s: float) -> None:
        self._compute = threading.BoundedSemaphore(compute)
        self._streams = threading.BoundedSemaphore(streams)
        self._limit_streams = streams
        self.queue_timeout_s = queue_timeout_s

    @contextmanager
    def compute(self, context, patient: bool = False) -> Iterator[None]:
        """A compute slot, waited for at most queue_timeout_s (and never past the deadline); a request
        whose client goes away meanwhile stops waiting (CANCELLED) instead of taking the slot.

        ``patient`` (pose streams): wait as long as the client is there; a stream's next frame simply
        comes later, and its newest pose replaces any it could not render meanwhile.
        """
        if patient:
            while not self._compute.acquire(timeout=POLL_S):
                if not context.is_active():
                    raise ResourceExhausted("the client went away while waiting for a compute slot")
        else:
            end = time.monotonic() + queue_wait(context, self.queue_timeout_s)
            while not self._compute.acquire(timeout=max(0.0, min(POLL_S, end - time.monotonic()))):
                if time.monotonic() >= end:
                    raise gave_up(context, "a compute slot", "server busy: no compute slot free; retry later")
                if not context.is_active():
                    raise Cancelled("the client went away while waiting for a compute slot")
        try:
            yield
        finally:
            self._compute.release()

    @contextmanager
    def stream(self) -> Iterator[None]:
        """A stream slot, or RESOURCE_EXHAUSTED at once when all are taken."""
        if not self._streams.acquire(blocking=False):
            raise ResourceExhausted(f"too many pose streams (limit {self._limit_streams})")
        try:
            yield
        finally:
            self._streams.release()

    def free_streams(self) -> int:
        """Stream slots free now."""
        return self._streams._value

    def free_compute(self) -> int:
        """Compute slots free now."""
        return self._compute._value
