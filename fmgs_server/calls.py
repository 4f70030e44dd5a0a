"""How a handler's outcome becomes a gRPC status and one log line (unary and streaming handlers)."""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Iterator

import grpc

from fmgs.errors import FmgsError, ValidationError
from fmgs.query.points import NoFieldError
from fmgs_server.errors import ServiceError

log = logging.getLogger("fmgs_server")


def status_of(e: BaseException) -> tuple[grpc.StatusCode, str]:
    """The status code and message for an exception raised while answering (README "Errors")."""
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
            code, msg = status_of(e)
            if code == grpc.StatusCode.INTERNAL:
                log.exception("%s failed", fn.__name__)
            context.abort(code, msg)
        finally:
            ms = (time.perf_counter() - t0) * 1e3
            log.info("%s scene=%s %s %.1f ms", fn.__name__, _scene_of(request), code.name, ms)

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
            code, text = status_of(e)
            if code == grpc.StatusCode.INTERNAL:
                log.exception("%s failed", fn.__name__)
            context.abort(code, text)
        finally:
            ms = (time.perf_counter() - t0) * 1e3
            log.info("%s scene=%s %s %d msgs %.1f ms", fn.__name__, _scene_of(request), code.name, n, ms)

    return wrapper
