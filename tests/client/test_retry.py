"""The client's channel retries reads that fail with UNAVAILABLE (gRPC's retry policy) and finds a server
that starts listening late within about its reconnect back-off cap; calls that change state are tried
once. Real grpc servers on loopback, answering UNAVAILABLE on purpose."""

from __future__ import annotations

import json
import os
import socket
import threading
import time
from concurrent import futures

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from fmgs_client import FmgsClient, FmgsError, RetryPolicy
from fmgs_client.retry import MAX_ATTEMPTS, READS, STREAM_READS, UNARY_READS, channel_options, service_config
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc


class Flaky(pb_grpc.FmgsServicer, health_pb2_grpc.HealthServicer):
    """Fails the first ``fails`` calls of each method with UNAVAILABLE, then answers."""

    def __init__(self, fails: int) -> None:
        self.fails = fails
        self.calls: dict[str, int] = {}
        self.lock = threading.Lock()

    def _count(self, name: str, context) -> bool:
        with self.lock:
            n = self.calls[name] = self.calls.get(name, 0) + 1
        if n <= self.fails:
            context.abort(grpc.StatusCode.UNAVAILABLE, f"{name} try {n} refused on purpose")
        return True

    def ListScenes(self, request, context):
        self._count("ListScenes", context)
        return pb.ListScenesResponse(scenes=[pb.SceneInfo(name="kitchen")])

    def LoadScene(self, request, context):
        self._count("LoadScene", context)
        return pb.SceneInfo(name=request.scene)

    def TextQuery(self, request, context):
        self._count("TextQuery", context)
        yield pb.TextQueryChunk(text_index=0, text="mug", total=0)

    def Check(self, request, context):
        self._count("Check", context)
        return health_pb2.HealthCheckResponse(status=health_pb2.HealthCheckResponse.SERVING)


def _serve(servicer, port: int = 0):
    srv = grpc.server(futures.ThreadPoolExecutor(4))
    pb_grpc.add_FmgsServicer_to_server(servicer, srv)
    health_pb2_grpc.add_HealthServicer_to_server(servicer, srv)
    port = srv.add_insecure_port(f"127.0.0.1:{port}")
    srv.start()
    return srv, port


@pytest.fixture
def flaky():
    servicer = Flaky(fails=2)
    srv, port = _serve(servicer)
    yield servicer, f"127.0.0.1:{port}"
    srv.stop(0)


def test_reads_are_retried_until_they_answer(flaky):
    servicer, address = flaky
    with FmgsClient(address, timeout=10, retry=RetryPolicy(attempts=3, initial_backoff_s=0.01)) as c:
        assert [s.name for s in c.list_scenes()] == ["kitchen"]
        assert c.health() == "SERVING"
    assert servicer.calls == {"ListScenes": 3, "Check": 3}


def test_streamed_reads_are_retried_before_their_first_message(flaky):
    servicer, address = flaky
    with FmgsClient(address, timeout=10, retry=RetryPolicy(attempts=3, initial_backoff_s=0.01)) as c:
        [answer] = c.query("kitchen", "mug")
    assert answer.text == "mug" and len(answer.index) == 0
    assert servicer.calls == {"TextQuery": 3}
    with FmgsClient(address, timeout=10, retry=RetryPolicy(attempts=2, initial_backoff_s=0.01)) as c:
        servicer.calls.clear()
        with pytest.raises(FmgsError, match="TextQuery try 2 refused"):
            c.query("kitchen", "mug")


def test_too_few_attempts_fail_with_the_servers_status(flaky):
    servicer, address = flaky
    with FmgsClient(address, timeout=10, retry=RetryPolicy(attempts=2, initial_backoff_s=0.01)) as c:
        with pytest.raises(FmgsError) as e:
            c.list_scenes()
    assert e.value.code == "UNAVAILABLE" and "try 2 refused" in e.value.details
    assert servicer.calls == {"ListScenes": 2}


def test_calls_that_change_state_and_a_disabled_policy_try_once(flaky):
    servicer, address = flaky
    with FmgsClient(address, timeout=10, retry=RetryPolicy(initial_backoff_s=0.01)) as c:
        with pytest.raises(FmgsError, match="LoadScene try 1"):
            c.load("kitchen")
    with FmgsClient(address, timeout=10, retry=RetryPolicy(attempts=1)) as c:
        with pytest.raises(FmgsError, match="ListScenes try 1"):
            c.list_scenes()
    assert servicer.calls == {"LoadScene": 1, "ListScenes": 1}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_server_that_starts_late_is_found_within_the_reconnect_cap():
    port = _free_port()
    policy = RetryPolicy(attempts=2, reconnect_initial_s=0.2, reconnect_max_s=0.5)
    with FmgsClient(f"127.0.0.1:{port}", timeout=5, retry=policy) as c:
        # Nothing listens: the channel fails and backs off (several failed connects grow the back-off
        # towards its cap, as during a proxy restart).
        deadline = time.monotonic() + 6.5
        while time.monotonic() < deadline:
            with pytest.raises(FmgsError) as e:
                c.health()
            assert e.value.code == "UNAVAILABLE"
            time.sleep(0.2)
        srv, _ = _serve(Flaky(fails=0), port)
        try:
            up = time.monotonic()
            while True:
                try:
                    assert c.health() == "SERVING"
                    break
                except FmgsError:
                    assert time.monotonic() - up < 0.5 + 1.25, "not found within the reconnect cap"
                    time.sleep(0.05)
        finally:
            srv.stop(0)


def test_the_service_config_names_only_reads_and_is_valid_json():
    cfg = service_config(RetryPolicy())
    [mc] = cfg["methodConfig"]
    names = {(n["service"], n["method"]) for n in mc["name"]}
    assert names == {("fmgs.v1.Fmgs", m) for m in UNARY_READS} | {("grpc.health.v1.Health", "Check")}
    writes = {"LoadScene", "UnloadScene", "ReloadScene", "StreamRender"}
    assert not writes & {m for _, m in names}
    assert set(READS) | writes == set(pb.DESCRIPTOR.services_by_name["Fmgs"].methods_by_name)
    assert (
        set(STREAM_READS)
        == {m.name for m in pb.DESCRIPTOR.services_by_name["Fmgs"].methods if m.server_streaming} - writes
    )
    assert mc["retryPolicy"]["retryableStatusCodes"] == ["UNAVAILABLE"]
    opts = dict(channel_options(RetryPolicy()))
    assert json.loads(opts["grpc.service_config"]) == cfg
    assert opts["grpc.max_reconnect_backoff_ms"] == 1000
    assert "grpc.service_config" not in dict(channel_options(RetryPolicy(attempts=1)))


@pytest.mark.parametrize(
    "bad",
    [
        {"attempts": 0},
        {"attempts": MAX_ATTEMPTS + 1},
        {"initial_backoff_s": 0},
        {"max_backoff_s": 0.1, "initial_backoff_s": 0.2},
        {"reconnect_max_s": 0.1},
        {"backoff_multiplier": 0.5},
    ],
)
def test_bad_policies_are_refused(bad):
    with pytest.raises(ValueError):
        RetryPolicy(**bad).validate()


SERVER = """
import sys, time
from concurrent import futures
import grpc
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb, fmgs_pb2_grpc as pb_grpc

class S(pb_grpc.FmgsServicer):
    def TextQuery(self, request, context):
        time.sleep(0.05)
        yield pb.TextQueryChunk(text_index=0, text="mug", total=0)

srv = grpc.server(futures.ThreadPoolExecutor(4))
pb_grpc.add_FmgsServicer_to_server(S(), srv)
srv.add_insecure_port("127.0.0.1:" + sys.argv[1])
srv.start()
print("up", flush=True)
srv.wait_for_termination()
"""


def test_streamed_reads_end_by_their_deadline_when_the_server_dies(tmp_path):
    """Closed-loop streamed queries while the server process is killed and, later, started again: every
    call ends (answer or error) within its deadline, and answers resume after the restart. grpcio's own
    stream retries (a service config on TextQuery) leave such calls hanging past their deadline."""
    import subprocess
    import sys
    from pathlib import Path

    script = tmp_path / "server.py"
    script.write_text(SERVER)
    port = _free_port()
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}

    def start():
        p = subprocess.Popen([sys.executable, str(script), str(port)], stdout=subprocess.PIPE, env=env)
        assert p.stdout.readline().strip() == b"up"
        return p

    proc = start()
    timeout, calls, stop = 2.0, [], threading.Event()

    def load():
        with FmgsClient(f"127.0.0.1:{port}", timeout=timeout) as c:
            while not stop.is_set():
                t = time.monotonic()
                try:
                    c.query("kitchen", "mug")
                    code = "OK"
                except FmgsError as e:
                    code = e.code
                calls.append((t, time.monotonic() - t, code))

    threads = [threading.Thread(target=load, daemon=True) for _ in range(3)]
    for t in threads:
        t.start()
    try:
        time.sleep(1.0)
        proc.kill()
        proc.wait()
        time.sleep(4.0)
        proc = start()
        restarted = time.monotonic()
        time.sleep(3.0)
    finally:
        stop.set()
        for t in threads:
            t.join(timeout + 2.0)
        proc.kill()
        proc.wait()
    assert not any(t.is_alive() for t in threads), "a call outlived its deadline"
    assert max(d for _, d, _ in calls) < timeout + 1.5
    assert {code for _, _, code in calls} <= {"OK", "UNAVAILABLE", "DEADLINE_EXCEEDED"}
    assert any(code == "UNAVAILABLE" for _, _, code in calls)
    assert any(code == "OK" and t > restarted for t, _, code in calls), "no answer after the restart"
