"""The working-memory budget of requests in flight (fmgs_server.budget): reserved before work, held
until the answer is consumed, shed with RESOURCE_EXHAUSTED; estimates grow with what a request asks."""

from __future__ import annotations

import threading
import time

import grpc
import numpy as np
import pytest

from fmgs.scene.package import load_scene
from fmgs_server import budget
from fmgs_server.budget import WorkBudget
from fmgs_server.config import ServerConfig
from fmgs_server.errors import ResourceExhausted
from fmgs_server.server import start_server
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc
from tests.helpers.contexts import FakeContext as Ctx
from tests.helpers.query_scenes import FakeEncoder, blob_scene


def test_reserve_sheds_waits_and_releases():
    b = WorkBudget(100, queue_timeout_s=0.05)
    with pytest.raises(ResourceExhausted, match="more than the server's work_memory_bytes"):
        with b.reserve(101, Ctx(), "x"):
            pass
    with b.reserve(60, Ctx(), "a"):
        assert b.used == 60
        with pytest.raises(ResourceExhausted, match="are free"):
            with b.reserve(50, Ctx(), "b"):
                pass
        with pytest.raises(ResourceExhausted, match="went away"):
            with b.reserve(50, Ctx(active=False), "c", patient=True):
                pass
        with b.reserve(40, Ctx(), "d"):
            assert b.used == 100
    assert b.used == 0
    got = threading.Event()
    hold = b.reserve(100, Ctx(), "e")
    hold.__enter__()

    def waiter():
        with b.reserve(30, Ctx(), "f", patient=True):
            got.set()

    t = threading.Thread(target=waiter)
    t.start()
    time.sleep(0.3)
    assert not got.is_set()
    hold.__exit__(None, None, None)
    t.join(5)
    assert got.is_set() and b.used == 0
    with WorkBudget(0, 1).reserve(10**15, Ctx(), "unlimited"):
        pass


def test_estimates_grow_with_the_request():
    assert budget.render_bytes(64, 64, ("relevancy",), False) < budget.render_bytes(
        128, 64, ("relevancy",), False
    )
    assert budget.render_bytes(64, 64, ("relevancy",), False) < budget.render_bytes(
        64, 64, ("relevancy", "rgb"), True
    )
    # A render projects every Gaussian of its scene (and scores the visible ones exactly on the compact path).
    assert (
        budget.render_bytes(64, 64, ("relevancy",), False, 1_000_000)
        - budget.render_bytes(64, 64, ("relevancy",), False)
        == 1_000_000 * budget.RENDER_BYTES_PER_GAUSSIAN
    )
    assert (
        budget.point_bytes(10_000, 1, 8192)
        < budget.point_bytes(20_000, 1, 8192)
        < budget.point_bytes(20_000, 2, 8192)
    )
    assert budget.point_bytes(10**6, 1, 8192) - budget.point_bytes(10**6 - 1, 1, 8192) < 1000  # chunked
    assert budget.text_bytes(100, 1, 0) < budget.text_bytes(1000, 1, 0) < budget.text_bytes(1000, 3, 6)


def test_a_stalled_reader_holds_its_memory_and_others_are_shed(tmp_path):
    root = tmp_path / "models"
    root.mkdir()
    blob_scene(root / "s")
    # A 32 MB answer: more than the transport buffers, so an unread answer stalls its generator.
    cam = pb.Camera(
        viewmat=np.eye(4).ravel().tolist(), fx=2000, fy=2000, cx=2000, cy=1000, width=4000, height=2000
    )
    gaussians = load_scene(root / "s").gaussians.num  # a render also counts its scene's Gaussians
    one = budget.render_bytes(4000, 2000, ("relevancy",), False, gaussians)
    cfg = ServerConfig(models=root, port=0, work_memory_bytes=int(1.05 * one), queue_timeout_s=0.2)
    srv = start_server(cfg, encoder_factory=lambda i: FakeEncoder())
    try:
        with grpc.insecure_channel(srv.address) as ch:
            stub = pb_grpc.FmgsStub(ch)
            req = pb.RenderRequest(scene="s", camera=cam, text="red cube")
            stalled = stub.Render(req, timeout=30)
            assert next(stalled).width == 4000  # the answer is under way; then nobody reads on
            deadline = time.monotonic() + 5
            while srv.service.budget.used == 0 and time.monotonic() < deadline:
                time.sleep(0.01)
            assert srv.service.budget.used == one
            with pytest.raises(grpc.RpcError) as e:
                list(stub.Render(req, timeout=30))
            assert (
                e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and "working memory" in e.value.details()
            )
            stalled.cancel()
            deadline = time.monotonic() + 5
            while srv.service.budget.used and time.monotonic() < deadline:
                time.sleep(0.01)
            assert srv.service.budget.used == 0  # released when the call ended
            assert list(stub.Render(req, timeout=30))[-1].last
            big = pb.Camera(
                viewmat=np.eye(4).ravel().tolist(), fx=400, fy=400, cx=400, cy=300, width=4096, height=2160
            )
            with pytest.raises(grpc.RpcError) as e:
                list(stub.Render(pb.RenderRequest(scene="s", camera=big, text="red cube"), timeout=30))
            assert (
                e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and "ask for less" in e.value.details()
            )
    finally:
        srv.stop(0)


@pytest.mark.slow
def test_a_large_point_query_stays_within_its_reserved_estimate():
    """Regression (issue 14): a large point query ran the whole batch through the field at once (13 KiB
    per point); now its peak RSS stays within what the budget reserves for it. Served from a subprocess
    (its own RSS) on the committed demo scene with its real text encoder."""
    from pathlib import Path

    from fmgs_server.launch import memory, reset_peak, subprocess_server
    from fmgs_wire.tensors import to_tensor

    models = Path(__file__).resolve().parents[2] / "models"
    n = 300_000
    pts = np.random.default_rng(0).normal(size=(n, 3)).astype(np.float32)
    with (
        subprocess_server(models) as (p, address),
        grpc.insecure_channel(address, options=[("grpc.max_receive_message_length", -1)]) as ch,
    ):
        stub = pb_grpc.FmgsStub(ch)
        stub.PointQuery(pb.PointQueryRequest(scene="demo", texts=["red cube"], points=to_tensor(pts[:100])))
        base = memory(p.pid)[0]
        reset_peak(p.pid)
        req = pb.PointQueryRequest(scene="demo", texts=["red cube", "blue ball"], points=to_tensor(pts))
        a = stub.PointQuery(req, timeout=300)
        peak = memory(p.pid)[1] - base
    assert len(a.relevancy.data) == 4 * 2 * n
    assert peak <= budget.point_bytes(n, 2, ServerConfig().point_chunk), peak / 2**20
