"""The request side of a bidirectional stream, read on its own thread: the newest request wins."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable
from typing import Generic, TypeVar

from fmgs_server.errors import InvalidArgument, UndecodableRequest

log = logging.getLogger("fmgs_server")
R = TypeVar("R")


class LatestRequest(Generic[R]):
    """Keeps only the newest unread request of a stream, so a client that sends poses faster than they
    render gets its latest pose next, never a backlog.

    ``next()`` returns that request, or None once the stream has ended (or the client has gone); a
    failure while reading (a malformed message) is raised by ``next()``: INVALID_ARGUMENT while the call
    is open, so it reaches the client as a status instead of ending the stream as if it were complete,
    or UndecodableRequest (INTERNAL, logged as such) when grpc has already ended the call for it.
    """

    def __init__(self, requests: Iterable[R], name: str = "fmgs-stream-reader") -> None:
        self._cond = threading.Condition()
        self._latest: R | None = None
        self._done = False
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._read, args=(requests,), daemon=True, name=name)
        self._thread.start()

    def _read(self, requests: Iterable[R]) -> None:
        try:
            for req in requests:
                with self._cond:
                    self._latest = req
                    self._cond.notify()
        except Exception as e:  # garbage on the wire, or the transport gave up
            log.info("stream reader stopped: %s: %s", type(e).__name__, e)
            with self._cond:
                self._error = e
        finally:
            with self._cond:
                self._done = True
                self._cond.notify()

    def next(self, is_active: Callable[[], bool], poll_s: float = 0.5) -> R | None:
        """The newest unread request; waits for one while ``is_active()``; None at the end."""
        with self._cond:
            while self._latest is None and not self._done:
                self._cond.wait(timeout=poll_s)
                if not is_active():
                    return None
            req, self._latest = self._latest, None
            if req is None and self._error is not None:
                why = f"request stream: could not read the next request ({self._error})"
                if not is_active():  # grpc has ended the call already (INTERNAL for undecodable bytes)
                    raise UndecodableRequest(why)
                raise InvalidArgument(why)
            return req
