"""Resource accounting over a call's life (fmgs_server.budget, fmgs_server.slots): working memory and
compute slots return to idle on every exit path, and a call whose client has gone stops waiting for them."""

from __future__ import annotations

import logging
import threading
import time

import grpc
import numpy as np
import pytest

from fmgs_server.config import ServerConfig
from fmgs_server.server import start_server
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc
from tests.helpers.contexts import FakeContext as Ctx
from tests.helpers.query_scenes import FakeEncoder, blob_scene

CAM = pb.Camera(viewmat=np.eye(4).ravel().tolist(), fx=40, fy=40, cx=24, cy=20, width=48, height=40)
RENDER = pb.RenderRequest(scene="s", camera=CAM, text="red cube")


@pytest.fixture()
def models(tmp_path):
    root = tmp_path / "models"
    root.mkdir()
    blob_scene(root / "s", with_field=True)
    return root


def _until(cond, timeout: float = 2.0) -> bool:
    """Poll ``cond`` until it holds or ``timeout`` seconds have passed; its last value."""
    end = time.monotonic() + timeout
    while not cond() and time.monotonic() < end:
        time.sleep(0.01)
    return bool(cond())


def _serve(models, **kw):
    cfg = ServerConfig(models=models, port=0, reload_check_s=0.0, **kw)
    return start_server(cfg, encoder_factory=lambda i: FakeEncoder())


def _idle(srv, slots: int) -> bool:
    s = srv.service
    return (
        s.budget.used == 0 and s.slots.free_compute() == slots and s.slots.free_streams() == s.cfg.max_streams
    )


def _logged(caplog, text: str) -> bool:
    return any(text in r.getMessage() for r in list(caplog.records))


def test_a_call_cancelled_while_queued_for_a_compute_slot_stops_waiting(models, caplog):
    """Regression: a call waiting for a compute slot kept waiting after its client cancelled, holding its
    working memory (and its place among max_concurrent_rpcs) for up to queue_timeout_s, and then took
    the slot to start work nobody would receive."""
    caplog.set_level(logging.INFO, logger="fmgs_server")
    srv = _serve(models, workers=1, queue_timeout_s=30.0)
    try:
        with grpc.insecure_channel(srv.address) as ch:
            stub = pb_grpc.FmgsStub(ch)
            assert list(stub.Render(RENDER, timeout=30))[-1].last  # loaded and compiled
            slots, budget = srv.service.slots, srv.service.budget
            assert _until(lambda: _idle(srv, 1))
            with slots.compute(Ctx()):  # every compute slot is busy
                call = stub.Render(RENDER, timeout=60)
                assert _until(lambda: budget.used > 0)  # reserved, now queued for the slot
                call.cancel()
                assert _until(lambda: budget.used == 0), "the cancelled call still holds its memory"
                assert _until(lambda: _logged(caplog, "Render scene=s CANCELLED"))
            assert slots.free_compute() == 1
            assert list(stub.Render(RENDER, timeout=30))[-1].last
            assert _until(lambda: _idle(srv, 1))
    finally:
        srv.stop(0)


def test_a_call_cancelled_while_queued_for_working_memory_stops_waiting(models, caplog):
    """Regression: a call waiting for working memory kept waiting for up to queue_timeout_s after its
    client cancelled, then took the memory and a compute slot."""
    caplog.set_level(logging.INFO, logger="fmgs_server")
    srv = _serve(models, workers=1, queue_timeout_s=30.0, work_memory_bytes=64 << 20)
    try:
        with grpc.insecure_channel(srv.address) as ch:
            stub = pb_grpc.FmgsStub(ch)
            assert list(stub.Render(RENDER, timeout=30))[-1].last
            budget = srv.service.budget
            waiting = threading.Event()
            reserve = budget.reserve

            def spy(nbytes, context, what, patient=False):
                waiting.set()
                return reserve(nbytes, context, what, patient)

            budget.reserve = spy
            with reserve(budget.total, Ctx(), "the test"):  # all the working memory is taken
                call = stub.Render(RENDER, timeout=60)
                assert waiting.wait(5)
                call.cancel()
                assert _until(lambda: _logged(caplog, "Render scene=s CANCELLED")), "still waiting"
                assert budget.used == budget.total
            assert _until(lambda: _idle(srv, 1))
            assert list(stub.Render(RENDER, timeout=30))[-1].last
            assert _until(lambda: _idle(srv, 1))
    finally:
        srv.stop(0)


def test_a_point_query_holds_its_memory_until_its_answer_is_sent(models, monkeypatch):
    """Regression: a point query released its working memory before it built its answer, whose copies
    (arrays, wire bytes, the serialised message) the estimate counts, so answers being built and sent
    were outside the budget."""
    from fmgs_server import budget as budget_mod
    from fmgs_server import server as server_mod
    from fmgs_wire.tensors import to_tensor

    seen, live = [], {}
    unary = server_mod._HANDLERS[(False, False)]

    def spy(fn, request_deserializer, response_serializer):
        def serialise(msg):
            if isinstance(msg, pb.PointQueryResponse):
                seen.append(live["srv"].service.budget.used)
            return response_serializer(msg)

        return unary(fn, request_deserializer=request_deserializer, response_serializer=serialise)

    monkeypatch.setitem(server_mod._HANDLERS, (False, False), spy)
    srv = live["srv"] = _serve(models, workers=1)
    try:
        with grpc.insecure_channel(srv.address) as ch:
            stub = pb_grpc.FmgsStub(ch)
            pts = np.random.default_rng(0).normal(size=(500, 3)).astype(np.float32)
            req = pb.PointQueryRequest(scene="s", texts=["red cube", "blue ball"], points=to_tensor(pts))
            a = stub.PointQuery(req, timeout=30)
            assert len(a.relevancy.data) == 4 * 2 * 500
            assert seen == [budget_mod.point_bytes(500, 2, srv.config.point_chunk)]
            assert _until(lambda: _idle(srv, 1))
            # Refused after reserving (no text at all is refused before): back to idle.
            req = pb.PointQueryRequest(scene="s", texts=["x"], points=to_tensor(pts), canonical_phrases=[""])
            with pytest.raises(grpc.RpcError) as e:
                stub.PointQuery(req, timeout=30)
            assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
            assert _until(lambda: _idle(srv, 1))
    finally:
        srv.stop(0)


def test_graceful_stop_ends_open_pose_streams_and_frees_everything(models):
    srv = _serve(models, workers=1)
    with grpc.insecure_channel(srv.address) as ch:
        stub = pb_grpc.FmgsStub(ch)
        gate = threading.Event()

        def poses():
            yield RENDER
            gate.wait(30)

        call = stub.StreamRender(poses(), timeout=60)
        assert next(call).sequence == 0
        t0 = time.monotonic()
        assert srv.stop(0.5)  # the open stream is cut after the grace period
        assert time.monotonic() - t0 < 0.5 + 2.0
        gate.set()
        with pytest.raises(grpc.RpcError):
            list(call)
        assert _until(lambda: _idle(srv, 1), 5.0)
