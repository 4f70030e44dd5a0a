"""fmgs_server.streams.LatestRequest: newest request wins, the end is None, a reader failure is a status."""

from __future__ import annotations

import threading
import time

import grpc
import pytest

from fmgs_server.errors import InvalidArgument, UndecodableRequest
from fmgs_server.streams import LatestRequest


def _gated(items, gate: threading.Event, fail: Exception | None = None):
    yield items[0]
    gate.wait(5)
    yield from items[1:]
    if fail is not None:
        raise fail


def test_newest_request_replaces_the_unread_ones():
    gate = threading.Event()
    r = LatestRequest(_gated([1, 2, 3, 4], gate))
    assert r.next(lambda: True) == 1
    gate.set()
    deadline = time.monotonic() + 5
    while r._thread.is_alive() and time.monotonic() < deadline:
        time.sleep(0.01)
    assert r.next(lambda: True) == 4  # 2 and 3 were superseded before anyone asked
    assert r.next(lambda: True) is None  # the stream ended


def test_reader_failure_reaches_the_caller_as_invalid_argument():
    gate = threading.Event()
    gate.set()
    r = LatestRequest(_gated([1, 2], gate, ValueError("Exception deserializing request!")))
    got = []
    with pytest.raises(InvalidArgument, match="deserializing") as e:
        while True:
            got.append(r.next(lambda: True))
            assert got[-1] is not None, "the failure must not look like the end of the stream"
    assert got[-1] == 2 and e.value.code == grpc.StatusCode.INVALID_ARGUMENT


def test_a_departed_client_ends_quietly():
    gate = threading.Event()  # never set: the reader blocks, as with a silent client
    r = LatestRequest(_gated([1], gate))
    assert r.next(lambda: True) == 1
    t0 = time.monotonic()
    assert r.next(lambda: False, poll_s=0.05) is None
    assert time.monotonic() - t0 < 2
    gate.set()


def test_failure_after_the_call_ended_is_reported_as_the_transports_status():
    gate = threading.Event()
    gate.set()
    r = LatestRequest(_gated([1], gate, RuntimeError("transport gone")))
    r._thread.join(5)
    assert r.next(lambda: True) == 1
    with pytest.raises(UndecodableRequest) as e:
        r.next(lambda: False)
    assert e.value.final and e.value.code == grpc.StatusCode.INTERNAL  # logged as grpc ended the call
