"""Exception types shared across the library."""

from __future__ import annotations


class FmgsError(Exception):
    """Base class for errors this project raises on purpose."""


class ValidationError(FmgsError, ValueError):
    """Input that breaks a documented contract (shape, finiteness, range).

    ``field`` names the offending input and ``index`` the first bad element (row), when there is one.
    """

    def __init__(self, field: str, reason: str, index: int | None = None) -> None:
        self.field = field
        self.reason = reason
        self.index = index
        where = f" at index {index}" if index is not None else ""
        super().__init__(f"{field}{where}: {reason}")


class BackendUnavailableError(FmgsError, RuntimeError):
    """An optional backend was requested but what it needs is missing."""
