"""A stand-in for grpc.ServicerContext: an optional deadline and whether the client is still there."""

from __future__ import annotations

import time


class FakeContext:
    """A call context with an optional deadline ``remaining`` seconds from now."""

    def __init__(self, remaining: float | None = None, active: bool = True) -> None:
        self.deadline = None if remaining is None else time.monotonic() + remaining
        self.active = active

    def time_remaining(self) -> float | None:
        return None if self.deadline is None else self.deadline - time.monotonic()

    def is_active(self) -> bool:
        return self.active
