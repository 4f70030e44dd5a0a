"""What a client is told when a Ray call behind the ingress fails: a short status of ours.

Ray's exception text carries colour codes, process ids, node addresses, actor ids and object reprs;
none of it reaches a client (the server log keeps it). A lost replica is ``UNAVAILABLE`` (gRPC's code
for "try again": clients with a retry policy do), and the ingress itself retries reads on another
replica before answering (:func:`retryable`).
"""

from __future__ import annotations

from fmgs_server.cluster.host import Status

REPLICA_LOST = Status("UNAVAILABLE", "the scene replica answering this call stopped; retry the call")
NO_REPLICA = Status("UNAVAILABLE", "no scene replica is available yet; retry the call")
QUEUE_FULL = Status("RESOURCE_EXHAUSTED", "the cluster's request queue is full; retry later")
CANCELLED = Status("CANCELLED", "the call was cancelled in the cluster")
REPLICA_FAILED = Status("INTERNAL", "the scene replica failed while answering (details in the server log)")

READS = frozenset(
    {"ListScenes", "GetScene", "PointQuery", "TextQuery", "Render", "Segment", "Geometry", "Check"}
)
"""Calls that change nothing: safe to run again on another replica."""


def _causes(exc: BaseException):
    """exc, then what it wraps (RayTaskError.cause, __cause__), outermost first, without cycles."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        yield e
        e = getattr(e, "cause", None) or e.__cause__


def failure_status(exc: BaseException) -> Status:
    """The status a client gets for an exception raised by a call to a Serve deployment."""
    from ray import exceptions as rx
    from ray.serve import exceptions as sx

    lost = (
        rx.RayActorError,  # ActorDiedError, ActorUnavailableError
        rx.WorkerCrashedError,
        rx.NodeDiedError,
        rx.LocalRayletDiedError,
        rx.ObjectLostError,  # OwnerDiedError among them: the answer's owner went away
        sx.ReplicaUnavailableError,
    )
    for e in _causes(exc):
        if isinstance(e, sx.BackPressureError):
            return QUEUE_FULL
        if isinstance(e, sx.DeploymentUnavailableError):
            return NO_REPLICA
        if isinstance(e, lost):
            return REPLICA_LOST
        if isinstance(e, rx.TaskCancelledError):
            return CANCELLED
    return REPLICA_FAILED


def retryable(method: str, status: Status) -> bool:
    """Whether ``method`` may run again after failing with ``status``: a read whose replica was lost."""
    return method in READS and status.code == "UNAVAILABLE"
