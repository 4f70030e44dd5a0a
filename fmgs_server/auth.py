"""Bearer-token access control as a server interceptor (tokens compared in constant time)."""

from __future__ import annotations

import hmac
from pathlib import Path

import grpc

from fmgs_server.config import ADMIN_CLOSED
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
    """Queries need a read or admin token when tokens are set; admin RPCs need an admin token, and are
    refused outright without admin tokens unless ``admin_open``; health may stay open.

    With ``admin_open`` (and no admin tokens) admin RPCs follow the query rules. With ``health_open``,
    the server's health (service "" and "fmgs.v1.Fmgs") needs no token; a scene's health
    ("fmgs.v1.Fmgs/<scene>") still does unless ``scene_health_open``, so scene names cannot be probed
    without a token.
    """

    def __init__(
        self,
        read: list[bytes],
        admin: list[bytes],
        health_open: bool = True,
        scene_health_open: bool = False,
        admin_open: bool = False,
    ) -> None:
        self.read, self.admin = read, admin
        self.health_open, self.scene_health_open = health_open, scene_health_open
        self.admin_open = admin_open and not admin

    @property
    def admin_closed(self) -> bool:
        """Admin RPCs are refused whatever the token: no admin tokens, and not opened."""
        return not self.admin and not self.admin_open

    def refusal(self, method: str, token: bytes) -> tuple[grpc.StatusCode, str] | None:
        """Why a call of ``method`` (full name) with bearer ``token`` (b"" for none) is refused, or None.
        Health calls are checked by ``health_refusal`` (it needs the service asked about)."""
        if method in ADMIN_METHODS and self.admin_closed:
            return grpc.StatusCode.PERMISSION_DENIED, ADMIN_CLOSED
        if not (self.read or self.admin):
            return None
        if method in ADMIN_METHODS and not self.admin_open:
            if not token:
                return grpc.StatusCode.UNAUTHENTICATED, "missing bearer token"
            if not _matches(token, self.admin):
                known = _matches(token, self.read)
                code = grpc.StatusCode.PERMISSION_DENIED if known else grpc.StatusCode.UNAUTHENTICATED
                return code, "admin token required" if known else "invalid bearer token"
            return None
        if not token:
            return grpc.StatusCode.UNAUTHENTICATED, "missing bearer token"
        if not (_matches(token, self.read) | _matches(token, self.admin)):
            return grpc.StatusCode.UNAUTHENTICATED, "invalid bearer token"
        return None

    def health_refusal(self, service: str, token: bytes) -> tuple[grpc.StatusCode, str] | None:
        """As ``refusal`` for a health check of ``service``."""
        if not (self.read or self.admin):
            return None
        if not self.health_open:
            return self.refusal(HEALTH_PREFIX + "Check", token)
        known = bool(token) and (_matches(token, self.read) | _matches(token, self.admin))
        if "/" in service and not (self.scene_health_open or known):
            return grpc.StatusCode.UNAUTHENTICATED, "a scene's health needs a bearer token"
        return None

    def intercept_service(self, continuation, details):
        handler = continuation(details)
        if handler is None:
            return None
        method = details.method
        if not (self.read or self.admin):
            if method in ADMIN_METHODS and self.admin_closed:
                return _deny(handler, grpc.StatusCode.PERMISSION_DENIED, ADMIN_CLOSED)
            return handler
        token = bearer_token(details.invocation_metadata)
        if self.health_open and method.startswith(HEALTH_PREFIX):
            known = bool(token) and (_matches(token, self.read) | _matches(token, self.admin))
            return handler if self.scene_health_open or known else _server_health_only(handler)
        refused = self.refusal(method, token)
        return handler if refused is None else _deny(handler, *refused)


def bearer_token(metadata) -> bytes:
    """The bearer token of a call's metadata (b"" when there is none)."""
    token = b""
    for key, value in metadata or ():
        if key == "authorization":
            v = value.encode() if isinstance(value, str) else value
            if v[:7].lower() == b"bearer ":
                token = v[7:].strip()
    return token


def _server_health_only(handler):
    """The health handler, refusing per-scene services ("fmgs.v1.Fmgs/<scene>") without a token."""

    def guard(fn):
        def call(request, context):
            if "/" in request.service:
                context.abort(grpc.StatusCode.UNAUTHENTICATED, "a scene's health needs a bearer token")
            return fn(request, context)

        return call

    if handler.unary_unary is not None:
        return handler._replace(unary_unary=guard(handler.unary_unary))
    if handler.unary_stream is not None:
        return handler._replace(unary_stream=guard(handler.unary_stream))
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
