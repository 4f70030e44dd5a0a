"""The Ray ingress's failure handling, driven directly (its class, a scripted stand-in for the scene
replicas' handle, a recording gRPC context): reads are tried again on a lost replica and end with our
UNAVAILABLE text when every try fails; calls that change state are tried once; anything else is INTERNAL
with our text; health asks a replica and says NOT_SERVING when none answers in time. The same code on a
real cluster: tests/server/test_cluster.py and benchmarks/faults.py."""

from __future__ import annotations

import asyncio

import grpc
import pytest
from grpc_health.v1 import health_pb2

from fmgs_server.cluster.config import ClusterConfig
from fmgs_server.cluster.faults import REPLICA_FAILED, REPLICA_LOST
from fmgs_server.config import ServerConfig
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb

ray = pytest.importorskip("ray", reason="the fmgs[ray] extra is part of the CI install")
from ray import exceptions as rx  # noqa: E402

SECRET = "10.1.2.3 pid=4242 ActorID(deadbeef)"
HANG = object()


class Host:
    """Stands in for the SceneHost handle: each call takes the next scripted outcome (an exception to
    raise, HANG, a value, or for streams a list of items, an exception among them raised there)."""

    def __init__(self, *outcomes) -> None:
        self.outcomes = list(outcomes)
        self.calls: list[str] = []

    def options(self, **kw):
        return self

    def __getattr__(self, name):
        host = self

        class Method:
            def remote(self, *args):
                host.calls.append(name)
                outcome = host.outcomes.pop(0) if len(host.outcomes) > 1 else host.outcomes[0]
                return _stream(outcome) if name == "stream" else _call(outcome)

        return Method()


async def _call(outcome):
    if outcome is HANG:
        await asyncio.sleep(60)
    if isinstance(outcome, BaseException):
        raise outcome
    return outcome


async def _stream(items):
    if isinstance(items, BaseException):
        raise items
    for x in items:
        if isinstance(x, BaseException):
            raise x
        yield x


class Context:
    def __init__(self) -> None:
        self.code, self._details, self.trailing = None, "", ()

    def invocation_metadata(self):
        return ()

    def set_code(self, code):
        self.code = code

    def set_details(self, details):
        self._details = details

    def details(self):
        return self._details

    def set_trailing_metadata(self, md):
        self.trailing = md


@pytest.fixture
def ingress(tmp_path, monkeypatch):
    import fmgs_server.cluster.app as app_module

    monkeypatch.setattr(app_module, "RETRY_PAUSE_S", 0.0)
    cc = ClusterConfig(read_attempts=3, health_timeout_s=0.3)
    classes = {}

    def make(host, admin_open=True):
        if admin_open not in classes:
            cfg = ServerConfig(models=tmp_path, admin_open=admin_open)
            classes[admin_open] = app_module.build_app(cfg, cc)._bound_deployment.func_or_class
        return classes[admin_open](host)

    return make


INFO = pb.SceneInfo(name="demo").SerializeToString()


def _unary(ingress, host, method, request):
    ctx = Context()
    out = asyncio.run(getattr(ingress(host), method)(request, ctx))
    return ctx, out


def test_a_read_is_tried_again_until_a_replica_answers(ingress, caplog):
    host = Host(rx.ActorDiedError(), rx.ActorUnavailableError(SECRET, None), ("r2", INFO))
    with caplog.at_level("WARNING", logger="ray.serve"):
        ctx, out = _unary(ingress, host, "GetScene", pb.SceneRequest(scene="demo"))
    assert ctx.code is None and out.SerializeToString() == INFO
    assert host.calls == ["unary"] * 3 and ("fmgs-replica", "r2") in ctx.trailing
    retries = [r.getMessage() for r in caplog.records if "trying again on another replica" in r.getMessage()]
    assert retries == [
        "GetScene: replica lost (UNAVAILABLE), trying again on another replica (try 2)",
        "GetScene: replica lost (UNAVAILABLE), trying again on another replica (try 3)",
    ]


def test_admin_calls_are_closed_unless_opened(ingress):
    """Serve's proxy listens on every interface: without an admin token file or admin_open, the ingress
    refuses admin calls itself and no replica is asked."""
    from fmgs_server.config import ADMIN_CLOSED

    for method in ("LoadScene", "UnloadScene", "ReloadScene"):
        host = Host(("r1", INFO))
        ctx = Context()
        asyncio.run(getattr(ingress(host, admin_open=False), method)(pb.SceneRequest(scene="demo"), ctx))
        assert (ctx.code, ctx.details()) == (grpc.StatusCode.PERMISSION_DENIED, ADMIN_CLOSED)
        assert host.calls == []
    ctx, out = _unary(ingress, Host(("r1", INFO)), "UnloadScene", pb.SceneRequest(scene="demo"))
    assert ctx.code is None and out.SerializeToString() == INFO


def test_a_read_that_fails_every_try_is_unavailable_with_our_text(ingress):
    host = Host(rx.RayTaskError("SceneHost.unary", SECRET, rx.ActorDiedError()).as_instanceof_cause())
    ctx, out = _unary(ingress, host, "GetScene", pb.SceneRequest(scene="demo"))
    assert ctx.code == grpc.StatusCode.UNAVAILABLE and ctx.details() == REPLICA_LOST.details
    assert out == pb.SceneInfo() and host.calls == ["unary"] * 3


def test_a_call_that_changes_state_is_tried_once(ingress):
    host = Host(rx.ActorDiedError(), ("r2", INFO))
    ctx, _ = _unary(ingress, host, "LoadScene", pb.SceneRequest(scene="demo"))
    assert ctx.code == grpc.StatusCode.UNAVAILABLE and host.calls == ["unary"]


def test_a_failure_inside_a_replica_is_internal_with_our_text(ingress):
    host = Host(rx.RayTaskError("SceneHost.unary", SECRET, ValueError(SECRET)).as_instanceof_cause())
    ctx, _ = _unary(ingress, host, "GetScene", pb.SceneRequest(scene="demo"))
    assert ctx.code == grpc.StatusCode.INTERNAL and ctx.details() == REPLICA_FAILED.details
    assert SECRET not in ctx.details() and host.calls == ["unary"]


def _drain(ingress, host, request):
    ctx = Context()

    async def run():
        out = []
        try:
            async for m in ingress(host).TextQuery(request, ctx):
                out.append(m.SerializeToString())
        except Exception as e:  # CallFailed ends a failed stream
            return out, e
        return out, None

    return ctx, *asyncio.run(run())


def test_a_stream_is_tried_again_only_before_its_first_message(ingress):
    req = pb.TextQueryRequest(scene="demo", texts=["mug"])
    host = Host(rx.ActorDiedError(), ["r1", rx.ActorDiedError()], ["r2", b"chunk-1", b"chunk-2"])
    ctx, out, err = _drain(ingress, host, req)
    assert err is None and ctx.code is None and out == [b"chunk-1", b"chunk-2"]
    assert host.calls == ["stream"] * 3
    # Lost after a message reached the client: UNAVAILABLE, not tried again (the client holds a part).
    host = Host(["r1", b"chunk-1", rx.ActorDiedError()], ["r2", b"chunk-1", b"chunk-2"])
    ctx, out, err = _drain(ingress, host, req)
    assert out == [b"chunk-1"] and type(err).__name__ == "CallFailed"
    assert ctx.code == grpc.StatusCode.UNAVAILABLE and ctx.details() == REPLICA_LOST.details
    assert host.calls == ["stream"]


@pytest.mark.parametrize(
    ("ping", "want"),
    [
        ("r1", health_pb2.HealthCheckResponse.SERVING),
        (rx.ActorDiedError(), health_pb2.HealthCheckResponse.NOT_SERVING),
        (HANG, health_pb2.HealthCheckResponse.NOT_SERVING),
    ],
    ids=["answers", "replicas-lost", "no-answer-in-time"],
)
def test_health_reflects_whether_a_scene_replica_answers(ingress, ping, want):
    host = Host(ping)
    ctx = Context()
    out = asyncio.run(ingress(host).Check(health_pb2.HealthCheckRequest(service=""), ctx))
    assert out.status == want and ctx.code is None
    assert host.calls[0] == "ping"
