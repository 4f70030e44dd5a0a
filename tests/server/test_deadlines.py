"""The server under hostile timing: SIGTERM after garbage on a bidirectional stream still exits within the
grace period (plus a bounded margin); work stops at the client's deadline and frees its compute slot; the
log line of every call carries the status the client saw."""

from __future__ import annotations

import logging
import signal
import subprocess
import threading
import time

import grpc
import numpy as np
import pytest

from fmgs_server.config import ServerConfig
from fmgs_server.launch import subprocess_server
from fmgs_server.server import STOP_MARGIN_S, start_server
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc
from fmgs_wire.tensors import to_tensor
from tests.helpers.query_scenes import FakeEncoder, blob_scene

GRACE_S = 1.0


def test_sigterm_after_garbage_on_a_stream_exits_within_grace(tmp_path):
    root = tmp_path / "m"
    root.mkdir()
    blob_scene(root / "s")
    with subprocess_server(root, "--grace-s", str(GRACE_S)) as (p, address):
        ch = grpc.insecure_channel(address)
        raw = ch.stream_stream(
            "/fmgs.v1.Fmgs/StreamRender", request_serializer=lambda b: b, response_deserializer=lambda b: b
        )
        gate = threading.Event()

        def garbage():
            for _ in range(3):
                yield b"\xff\xff\xff\xff\x0f garbage"
            gate.wait(60)  # keep the stream open

        def call():
            try:
                for _ in raw(garbage()):
                    pass
            except grpc.RpcError:
                pass

        threading.Thread(target=call, daemon=True).start()
        time.sleep(1.0)
        t0 = time.monotonic()
        p.send_signal(signal.SIGTERM)
        try:
            rc = p.wait(timeout=GRACE_S + STOP_MARGIN_S + 5)
        except subprocess.TimeoutExpired:
            pytest.fail("the server did not exit within grace + 5 s of SIGTERM")
        took = time.monotonic() - t0
        assert rc == 0 and took <= GRACE_S + STOP_MARGIN_S + 5, took
        gate.set()
        ch.close()


@pytest.fixture()
def served(tmp_path):
    root = tmp_path / "models"
    root.mkdir()
    blob_scene(root / "f", with_field=True)
    srv = start_server(
        ServerConfig(models=root, port=0, workers=1, point_chunk=64), encoder_factory=lambda i: FakeEncoder()
    )
    ch = grpc.insecure_channel(srv.address)
    yield srv, pb_grpc.FmgsStub(ch)
    ch.close()
    srv.stop(0)


def _slot_free_after(srv, t_deadline: float, limit: float = 5.0) -> float:
    """Seconds from the client's deadline until the compute slot is free again."""
    while srv.service.slots.free_compute() == 0 and time.monotonic() < t_deadline + limit:
        time.sleep(0.01)
    assert srv.service.slots.free_compute() == 1
    return time.monotonic() - t_deadline


def _log_line(caplog, rpc: str, since: int = 0) -> str:
    """The last access-log line for `rpc` among records from index `since` on (the
    line is written after the client has seen the status, so wait for it)."""
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
        lines = [r.getMessage() for r in caplog.records[since:] if r.getMessage().startswith(rpc + " ")]
        if lines:
            return lines[-1]
        time.sleep(0.02)
    raise AssertionError(f"no log line for {rpc}")


def test_point_query_stops_at_its_deadline_and_logs_it(served, caplog):
    caplog.set_level(logging.INFO, logger="fmgs_server")
    srv, stub = served
    pts = np.random.default_rng(0).normal(size=(200_000, 3)).astype(np.float32)
    req = pb.PointQueryRequest(scene="f", texts=["red cube"], points=to_tensor(pts))
    stub.PointQuery(pb.PointQueryRequest(scene="f", texts=["red cube"], points=to_tensor(pts[:10])))  # load
    since = len(caplog.records)
    timeout = 0.5
    t0 = time.monotonic()
    with pytest.raises(grpc.RpcError) as e:
        stub.PointQuery(req, timeout=timeout)
    assert e.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
    assert _slot_free_after(srv, t0 + timeout) < 0.5
    assert "DEADLINE_EXCEEDED" in _log_line(caplog, "PointQuery", since)


def test_text_query_stops_between_texts(served, caplog, monkeypatch):
    caplog.set_level(logging.INFO, logger="fmgs_server")
    srv, stub = served
    list(stub.TextQuery(pb.TextQueryRequest(scene="f", texts=["red cube"], top_k=5)))  # load
    import fmgs.query.plan as plan

    slow = plan.certify_start

    def certify_start(*a, **k):  # each text's certification takes 0.2 s
        time.sleep(0.2)
        return slow(*a, **k)

    monkeypatch.setattr(plan, "certify_start", certify_start)
    since = len(caplog.records)  # the loading call's line is not this call's
    timeout = 0.5
    t0 = time.monotonic()
    with pytest.raises(grpc.RpcError) as e:
        list(
            stub.TextQuery(pb.TextQueryRequest(scene="f", texts=["red cube"] * 40, top_k=5), timeout=timeout)
        )
    assert e.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
    assert _slot_free_after(srv, t0 + timeout) < 0.5  # not the 8 s the 40 texts would take
    assert "DEADLINE_EXCEEDED" in _log_line(caplog, "TextQuery", since)


def test_cancelled_stream_is_logged_as_cancelled(served, caplog):
    caplog.set_level(logging.INFO, logger="fmgs_server")
    _, stub = served
    cam = pb.Camera(viewmat=np.eye(4).ravel().tolist(), fx=40, fy=40, cx=24, cy=20, width=48, height=40)
    gate = threading.Event()

    def poses():
        yield pb.RenderRequest(scene="f", camera=cam, text="red cube")
        gate.wait(10)

    it = stub.StreamRender(poses())
    assert next(it).sequence == 0
    it.cancel()
    gate.set()
    line = _log_line(caplog, "StreamRender")
    assert "CANCELLED" in line and " OK " not in line


def test_too_large_point_answer_is_refused_before_work(served):
    srv, stub = served
    n = srv.config.max_send_bytes // (8 * 64) + 1  # 64 texts x n points x 8 bytes > max_send_bytes
    pts = np.zeros((min(n, srv.config.max_points), 3), np.float32)
    req = pb.PointQueryRequest(scene="f", texts=["t"] * 64, points=to_tensor(pts))
    with pytest.raises(grpc.RpcError) as e:
        stub.PointQuery(req)
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "max_send_bytes" in e.value.details()


def test_garbage_on_a_pose_stream_is_invalid_argument_and_logged_so(served, caplog):
    caplog.set_level(logging.INFO, logger="fmgs_server")
    srv, _ = served
    with grpc.insecure_channel(srv.address) as ch:
        raw = ch.stream_stream(
            "/fmgs.v1.Fmgs/StreamRender", request_serializer=lambda b: b, response_deserializer=lambda b: b
        )
        with pytest.raises(grpc.RpcError) as e:
            list(raw(iter([b"\xff\xff\xff\xff\x0f garbage"]), timeout=10))
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "request stream" in e.value.details()
    line = _log_line(caplog, "StreamRender")
    assert "INVALID_ARGUMENT" in line
    assert srv.service.slots.free_streams() == srv.config.max_streams


def test_maximum_render_stops_at_its_deadline(served, caplog):
    caplog.set_level(logging.INFO, logger="fmgs_server")
    srv, stub = served
    cam = pb.Camera(
        viewmat=np.eye(4).ravel().tolist(), fx=2000, fy=2000, cx=2048, cy=1080, width=4096, height=2160
    )
    outputs = [
        pb.RENDER_OUTPUT_RELEVANCY,
        pb.RENDER_OUTPUT_RGB,
        pb.RENDER_OUTPUT_DEPTH,
        pb.RENDER_OUTPUT_ALPHA,
    ]
    req = pb.RenderRequest(scene="f", camera=cam, text="red cube", outputs=outputs)
    list(stub.Render(pb.RenderRequest(scene="f", camera=camera_small(), text="red cube")))  # load, compile
    since = len(caplog.records)
    timeout = 0.3
    t0 = time.monotonic()
    with pytest.raises(grpc.RpcError) as e:
        list(stub.Render(req, timeout=timeout))
    assert e.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
    assert _slot_free_after(srv, t0 + timeout) < 0.5
    assert "DEADLINE_EXCEEDED" in _log_line(caplog, "Render", since)


def camera_small() -> pb.Camera:
    return pb.Camera(viewmat=np.eye(4).ravel().tolist(), fx=40, fy=40, cx=24, cy=20, width=48, height=40)
