"""Bearer-token access control as a server interceptor (tokens compared in constant time)."""

from __future__ import annotations

import hmac
from pathlib import Path

import grpc

from fmgs_wire.tokens import read_token_file

ADMIN_METHODS = frozenset(
    {"/fmgs.v1.Fmgs/LoadScene", "/fmgs.v1.Fmgs/UnloadScene", "/fmgs.v1.Fmgs/ReloadScene"}
)
HEALTH_PREFIX = "/grpc.health.v1.Health/"


def read_tokens(path: Path | None) -> list[bytes]:
    """Tokens from a file, one per line (blank lines and '#' comments ignored); [] when path is None."""
    if path is None:
        return []
    return [t.encode() for t in read_token_file(path)]


def _matches(token: bytes, allowed: list[bytes]) -> bool:
    ok = False
    for t in allowed:  # no early exit: time does not depend on which token matched
        ok |= hmac.compare_digest(token, t)
    return ok


class TokenAuth(grpc.ServerInterceptor):
    """Queries need a read or admin token; admin RPCs need an admin token; health may stay open."""

    def __init__(self, read: list[bytes], admin: list[bytes], health_open: bool = True) -> None:
        self.read, self.admin, self.health_open = read, admin, health_open

    def intercept_service(self, continuation, details):
        handler = continuation(details)
        if handler is None:
            return None
        method = details.method
        if (self.health_open and method.startswith(HEALTH_PREFIX)) or not (self.read or self.admin):
            return handler
        token = b""
        for key, value in details.invocation_metadata or ():
            if key == "authorization":
                v = value.encode() if isinstance(value, str) else value
                if v[:7].lower() == b"bearer ":
                    token = v[7:].strip()
        if method in ADMIN_METHODS:
            if not token:
                return _deny(handler, grpc.StatusCode.UNAUTHENTICATED, "missing bearer token")
            if not self.admin or not _matches(token, self.admin):
                known = _matches(token, self.read)
                code = grpc.StatusCode.PERMISSION_DENIED if known else grpc.StatusCode.UNAUTHENTICATED
                return _deny(handler, code, "admin token required" if known else "invalid bearer token")
            return handler
        if not token:
            return _deny(handler, grpc.StatusCode.UNAUTHENTICATED, "missing bearer token")
        if not (_matches(token, self.read) | _matches(token, self.admin)):
            return _deny(handler, grpc.StatusCode.UNAUTHENTICATED, "invalid bearer token")
        return handler


def _deny(handler, code: grpc.StatusCode, message: str):
    """A handler of the same kind as ``handler`` that aborts with ``code``."""

    def abort(request, context):
        context.abort(code, message)

    def abort_stream(request, context):
        context.abort(code, message)
        yield  # pragma: no cover

    kind = {
        "unary_unary": abort,
        "unary_stream": abort_stream,
        "stream_unary": abort,
        "stream_stream": abort_stream,
    }
    for name, fn in kind.items():
        if getattr(handler, name) is not None:
            return handler._replace(**{name: fn})
    return handler
