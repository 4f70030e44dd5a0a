"""Ray failures become short statuses of ours (no Ray text, address, id or repr reaches a client), and
only reads whose replica was lost are tried again. Real Ray exception objects, no cluster."""

from __future__ import annotations

import re

import pytest

from fmgs_server.cluster.faults import (
    CANCELLED,
    NO_REPLICA,
    QUEUE_FULL,
    READS,
    REPLICA_FAILED,
    REPLICA_LOST,
    failure_status,
    retryable,
)
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb

rx = pytest.importorskip("ray.exceptions", reason="the fmgs[ray] extra is part of the CI install")
sx = pytest.importorskip("ray.serve.exceptions")

SECRET = "10.1.2.3 pid=4242 ActorID(deadbeef) <object at 0x7f00>"


def _task_error(cause: BaseException):
    """How a failure inside a replica reaches the ingress: RayTaskError wrapping it, with Ray's text."""
    return rx.RayTaskError("SceneHost.unary", f"Traceback ... {SECRET}", cause, ip="10.1.2.3", pid=4242)


LOST = [
    rx.ActorDiedError(),
    rx.ActorUnavailableError(f"unreachable {SECRET}", b"\x01" * 16),
    rx.WorkerCrashedError(),
    rx.NodeDiedError(SECRET),
    rx.OwnerDiedError("ab" * 14, None, SECRET),
    sx.ReplicaUnavailableError(SECRET),
    _task_error(rx.ActorDiedError()).as_instanceof_cause(),
]


@pytest.mark.parametrize("exc", LOST, ids=lambda e: type(e).__name__)
def test_a_lost_replica_is_unavailable_and_reads_are_retried(exc):
    status = failure_status(exc)
    assert status == REPLICA_LOST and status.code == "UNAVAILABLE"
    assert retryable("TextQuery", status) and retryable("Check", status)
    assert not retryable("LoadScene", status) and not retryable("ReloadScene", status)


def test_a_lost_replica_wrapped_by_python_chaining_is_still_lost():
    try:
        try:
            raise rx.ActorDiedError()
        except rx.ActorDiedError as inner:
            raise RuntimeError(SECRET) from inner
    except RuntimeError as outer:
        assert failure_status(outer) == REPLICA_LOST


@pytest.mark.parametrize(
    ("exc", "want"),
    [
        (sx.BackPressureError(num_queued_requests=9, max_queued_requests=8), QUEUE_FULL),
        (sx.DeploymentUnavailableError("SceneHost"), NO_REPLICA),
        (sx.RequestCancelledError(SECRET), CANCELLED),
        (_task_error(ValueError(SECRET)).as_instanceof_cause(), REPLICA_FAILED),
        (RuntimeError(SECRET), REPLICA_FAILED),
    ],
    ids=lambda x: type(x).__name__,
)
def test_other_failures_get_their_own_status(exc, want):
    status = failure_status(exc)
    assert status == want
    assert retryable("TextQuery", status) == (want.code == "UNAVAILABLE")


def test_no_status_text_carries_internals():
    for status in (REPLICA_LOST, NO_REPLICA, QUEUE_FULL, CANCELLED, REPLICA_FAILED):
        text = status.details
        assert len(text) < 100 and "\x1b" not in text
        assert not re.search(r"\d+\.\d+\.\d+\.\d+|0x[0-9a-f]+|pid|actor|ray", text, re.I), text


def test_reads_are_exactly_the_methods_that_change_nothing():
    methods = set(pb.DESCRIPTOR.services_by_name["Fmgs"].methods_by_name)
    changes = {"LoadScene", "UnloadScene", "ReloadScene", "StreamRender"}
    assert READS == (methods - changes) | {"Check"}
