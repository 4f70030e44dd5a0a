"""How a handler's outcome becomes a gRPC status and one log line (unary and streaming handlers)."""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Iterator

import grpc

from fmgs.errors import FmgsError, ValidationError
from fmgs.query.points import NoFieldError
from fmgs_server.errors import Cancelled, DeadlineExceeded, ServiceError

log = logging.getLogger("fmgs_server")

STREAM_END_GRACE_S = 0.05
"""When a client's request stream ends, how long a request-streaming handler waits for a cancellation
to land before calling the end normal. grpc reports a client's cancel to the server as the end of its
request stream first and as a cancellation a moment later; without the wait a cancelled pose stream
could be logged OK (the client saw CANCELLED). Paid once, at the end of a stream."""


def status_of(e: BaseException) -> tuple[grpc.StatusCode, str]:
    """The status code and message for an exception raised while answering (docs/serving.md, "Errors")."""
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


DEADLINE_SLACK_S = 0.05
"""A client's deadline runs from when it starts the call, the server's from when the call arrives, so
the client gives up (and its cancel reaches the server) a few milliseconds before the server's own
deadline passes; a call that ended this close to its deadline was ended by it (seen: a 0.5 s call
ended with 11 ms of the server's deadline left, and was logged CANCELLED)."""


def seen_by_client(context, code: grpc.StatusCode) -> grpc.StatusCode:
    """The status the client saw: once the call is over, its deadline (passed, or within
    ``DEADLINE_SLACK_S``) or its cancellation wins over whatever the handler produced."""
    if context.is_active():
        return code
    left = context.time_remaining()
    ended_by_deadline = left is not None and left <= DEADLINE_SLACK_S
    return grpc.StatusCode.DEADLINE_EXCEEDED if ended_by_deadline else grpc.StatusCode.CANCELLED


def stop_if_gone(context, where: str) -> None:
    """Between stages of long work: stop (freeing the compute slot) once the client's deadline has passed
    or the client has gone, instead of finishing an answer nobody receives."""
    left = context.time_remaining()
    if left is not None and left <= 0:
        raise DeadlineExceeded(f"the deadline passed during {where}")
    if not context.is_active():
        raise Cancelled(f"the client went away during {where}")


def _failed(name: str, e: Exception, context) -> tuple[grpc.StatusCode, str]:
    """The status to abort with for handler error ``e`` and the one to log (what the client saw, unless
    the transport has already ended the call with the error's own code)."""
    code, text = status_of(e)
    final = getattr(e, "final", False)
    if code == grpc.StatusCode.INTERNAL and not final:
        log.exception("%s failed", name)
    return (code if final else seen_by_client(context, code)), text


def _scene_of(request) -> str:
    return getattr(request, "scene", "") if not isinstance(request, Iterator) else ""


def rpc(fn):
    """Unary handler: map errors to status codes, log one line with timing and the status the client saw."""

    @functools.wraps(fn)
    def wrapper(self, request, context):
        t0 = time.perf_counter()
        code = grpc.StatusCode.OK
        try:
            answer = fn(self, request, context)
            code = seen_by_client(context, code)
            return answer
        except Exception as e:
            code, text = _failed(fn.__name__, e, context)
            context.abort(code, text)
        finally:
            ms = (time.perf_counter() - t0) * 1e3
            log.info("%s scene=%s %s %.1f ms", fn.__name__, _scene_of(request), code.name, ms)

    return wrapper


def _settle(context) -> None:
    """Wait up to STREAM_END_GRACE_S while the call is still active."""
    end = time.monotonic() + STREAM_END_GRACE_S
    while context.is_active() and time.monotonic() < end:
        time.sleep(0.005)


def rpc_stream(fn):
    """Streaming handler: as ``rpc`` for generators; stops quietly when the client has gone (logged as
    CANCELLED, or DEADLINE_EXCEEDED when its deadline ended the call)."""

    @functools.wraps(fn)
    def wrapper(self, request, context):
        t0 = time.perf_counter()
        code, n = grpc.StatusCode.OK, 0
        try:
            for msg in fn(self, request, context):
                if not context.is_active():
                    code = seen_by_client(context, grpc.StatusCode.CANCELLED)
                    return
                n += 1
                yield msg
            if isinstance(request, Iterator):
                _settle(context)
            code = seen_by_client(context, code)
        except GeneratorExit:  # the transport closed the stream: the client left or its deadline passed
            code = seen_by_client(context, grpc.StatusCode.CANCELLED)
            raise
        except Exception as e:
            code, text = _failed(fn.__name__, e, context)
            context.abort(code, text)
        finally:
            ms = (time.perf_counter() - t0) * 1e3
            log.info("%s scene=%s %s %d msgs %.1f ms", fn.__name__, _scene_of(request), code.name, n, ms)

    return wrapper
