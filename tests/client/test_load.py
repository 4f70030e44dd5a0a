"""Load on loopback: 32 concurrent clients with zero errors, load shedding beyond capacity, a flat soak."""

from __future__ import annotations

import gc

import numpy as np
import psutil
import pytest

from fmgs_client.load import LoadConfig, run_load
from fmgs_server.config import ServerConfig
from fmgs_server.server import start_server
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from tests.helpers.query_scenes import CLASS_NAMES, FakeEncoder, blob_scene

CAM = pb.Camera(viewmat=np.eye(4).ravel().tolist(), fx=40, fy=40, cx=32, cy=24, width=64, height=48)


@pytest.fixture()
def models(tmp_path):
    root = tmp_path / "models"
    root.mkdir()
    blob_scene(root / "blobs")
    return root


def _server(models, **kw):
    return start_server(ServerConfig(models=models, port=0, **kw), encoder_factory=lambda i: FakeEncoder())


def test_32_clients_zero_errors(models):
    srv = _server(models)
    try:
        rep = run_load(srv.address, LoadConfig("blobs", CLASS_NAMES, CAM, clients=32, requests=640))
    finally:
        srv.stop(0)
    print(rep.summary())
    assert rep.sent == 640 and rep.errors == 0, rep.codes
    assert rep.percentile(99) >= rep.percentile(50) > 0


def test_beyond_capacity_sheds_with_resource_exhausted(models):
    srv = _server(models, max_concurrent_rpcs=4, workers=1, queue_timeout_s=0.05)
    try:
        cfg = LoadConfig("blobs", CLASS_NAMES, CAM, clients=32, requests=640, render_every=1)
        rep = run_load(srv.address, cfg)
    finally:
        srv.stop(0)
    print(rep.summary())
    assert set(rep.codes) <= {"OK", "RESOURCE_EXHAUSTED"}, rep.codes
    assert rep.codes["RESOURCE_EXHAUSTED"] > 0 and rep.ok > 0


@pytest.mark.slow
def test_soak_10000_requests_memory_flat(models):
    srv = _server(models)
    proc = psutil.Process()
    try:
        cfg = LoadConfig("blobs", CLASS_NAMES, CAM, clients=8, requests=2000, render_every=10)
        warm = run_load(srv.address, cfg)
        gc.collect()
        rss0 = proc.memory_info().rss
        soak = run_load(
            srv.address, LoadConfig("blobs", CLASS_NAMES, CAM, clients=8, requests=10_000, render_every=10)
        )
        gc.collect()
        rss1 = proc.memory_info().rss
    finally:
        srv.stop(0)
    print(warm.summary(), soak.summary(), f"rss {rss0 / 2**20:.1f} -> {rss1 / 2**20:.1f} MiB")
    assert warm.errors == 0 and soak.errors == 0 and soak.sent == 10_000
    assert rss1 - rss0 < 32 * 2**20, (rss0, rss1)


def test_a_run_without_an_ok_request_has_no_percentile_and_says_so():
    from fmgs_client.load import LoadReport

    rep = LoadReport(sent=3, ok=0, seconds=1.0)
    assert rep.percentile(50) is None and rep.percentile(99) is None  # not NaN: stored reports are JSON
    assert "no latencies" in rep.summary()
    rep.latencies_ms = [5.0, 1.0, 3.0]
    assert (rep.percentile(0), rep.percentile(50), rep.percentile(100)) == (1.0, 3.0, 5.0)
    with pytest.raises(ValueError, match="percentile"):
        rep.percentile(101)
