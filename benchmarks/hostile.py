"""Hostile-load figures for RELIABILITY.md: shutdown time after hostile calls, time from a client's deadline
to the release of its compute slot, and peak RSS of the worst request of each kind the limits allow.

    python -m benchmarks.reliability --only hostile     # merges into RELIABILITY.json / .md

Every figure is taken on the product: ``fmgs-server`` subprocesses (shutdown, RSS) or ``start_server``
in-process (slot release, read from its slots), serving models/demo with the real MiniLM encoder.
"""

from __future__ import annotations

import signal
import subprocess
import threading
import time
from pathlib import Path

import grpc
import numpy as np

from fmgs_server import budget
from fmgs_server.config import ServerConfig
from fmgs_server.launch import memory, reset_peak, subprocess_server
from fmgs_server.server import STOP_MARGIN_S, start_server
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc
from fmgs_wire.tensors import to_tensor

GRACE_S = 2.0
MAX_W, MAX_H = 4096, 2160
CLIENT_OPTIONS = [("grpc.max_receive_message_length", -1)]
"""The measuring client takes any answer the server may send (a PNG answer is one message)."""
ALL_OUTPUTS = [
    pb.RENDER_OUTPUT_RELEVANCY,
    pb.RENDER_OUTPUT_RGB,
    pb.RENDER_OUTPUT_DEPTH,
    pb.RENDER_OUTPUT_ALPHA,
]


def camera(cam: pb.Camera, w: int, h: int) -> pb.Camera:
    """``cam`` (the demo's view) at another size, same field of view."""
    s = w / cam.width
    return pb.Camera(viewmat=cam.viewmat, fx=cam.fx * s, fy=cam.fy * s, cx=w / 2, cy=h / 2, width=w, height=h)


def shutdown_after(models: Path, hostile) -> float:
    """Seconds from SIGTERM to exit with ``hostile(address)`` calls in flight (inf: killed after 60 s)."""
    with subprocess_server(models, "--grace-s", str(GRACE_S), "--preload") as (p, address):
        stop = hostile(address)
        time.sleep(1.5)
        t0 = time.monotonic()
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(timeout=60)
            took = time.monotonic() - t0
        except subprocess.TimeoutExpired:
            took = float("inf")
        stop()
        return took


def _idle(address):
    return lambda: None


def _garbage_streams(address):
    ch = grpc.insecure_channel(address)
    raw = ch.stream_stream(
        "/fmgs.v1.Fmgs/StreamRender", request_serializer=lambda b: b, response_deserializer=lambda b: b
    )
    gate = threading.Event()

    def garbage():
        yield b"\xff\xff\xff\xff\x0f garbage"
        gate.wait(120)

    def call():
        try:
            list(raw(garbage()))
        except grpc.RpcError:
            pass

    for _ in range(3):
        threading.Thread(target=call, daemon=True).start()
    return lambda: (gate.set(), ch.close())


def _stalled_renders(cam: pb.Camera):
    def start(address):
        ch = grpc.insecure_channel(address)
        stub = pb_grpc.FmgsStub(ch)
        req = pb.RenderRequest(scene="demo", camera=camera(cam, MAX_W, MAX_H), text="red cube")
        calls = [stub.Render(req, timeout=120) for _ in range(4)]
        for c in calls:  # the first chunk, then nobody reads on
            threading.Thread(target=lambda c=c: next(c, None), daemon=True).start()
        return lambda: ([c.cancel() for c in calls], ch.close())

    return start


def _long_points(address):
    ch = grpc.insecure_channel(address)
    pts = np.random.default_rng(0).uniform(-1, 1, size=(1_000_000, 3)).astype(np.float32)
    fut = pb_grpc.FmgsStub(ch).PointQuery.future(
        pb.PointQueryRequest(scene="demo", texts=["red cube"] * 8, points=to_tensor(pts)), timeout=300
    )
    return lambda: (fut.cancel(), ch.close())


def shutdowns(models: Path, cam: pb.Camera) -> dict[str, float]:
    cases = {
        "idle": _idle,
        "3 pose streams that sent garbage, kept open": _garbage_streams,
        f"4 stalled {MAX_W}x{MAX_H} renders (first chunk read, then none)": _stalled_renders(cam),
        "a 1M-point x 8-text point query in flight": _long_points,
    }
    return {name: shutdown_after(models, fn) for name, fn in cases.items()}


def slot_releases(models: Path, cam: pb.Camera, texts: tuple[str, ...]) -> dict[str, dict]:
    """Per RPC: the client's timeout, what it saw, and seconds from its deadline to the slot's release."""
    srv = start_server(ServerConfig(models=models, port=0, workers=1, preload=True))
    out = {}
    try:
        with grpc.insecure_channel(srv.address, options=CLIENT_OPTIONS) as ch:
            stub = pb_grpc.FmgsStub(ch)
            pts = np.random.default_rng(1).uniform(-1, 1, size=(1_000_000, 3)).astype(np.float32)
            many = [f"{t} {i}" for i in range(11) for t in texts][:64]
            cases = {
                f"Render {MAX_W}x{MAX_H}, all outputs": (
                    lambda t: list(
                        stub.Render(
                            pb.RenderRequest(
                                scene="demo",
                                camera=camera(cam, MAX_W, MAX_H),
                                text="red cube",
                                outputs=ALL_OUTPUTS,
                            ),
                            timeout=t,
                        )
                    ),
                    1.0,
                ),
                "TextQuery, 64 new texts, all Gaussians, instances": (
                    lambda t: list(
                        stub.TextQuery(
                            pb.TextQueryRequest(
                                scene="demo",
                                texts=many,
                                top_k=1_000_000,
                                instances=pb.InstanceOptions(enabled=True),
                            ),
                            timeout=t,
                        )
                    ),
                    0.5,
                ),
                "PointQuery, 1M points x 8 texts": (
                    lambda t: stub.PointQuery(
                        pb.PointQueryRequest(scene="demo", texts=list(texts[:1]) * 8, points=to_tensor(pts)),
                        timeout=t,
                    ),
                    1.0,
                ),
                "Segment 4096x2160, 16 classes": (
                    lambda t: list(
                        stub.Segment(
                            pb.SegmentRequest(
                                scene="demo",
                                class_names=[f"{x} {i}" for i in range(3) for x in texts][:16],
                                camera=camera(cam, MAX_W, MAX_H),
                            ),
                            timeout=t,
                        )
                    ),
                    0.5,
                ),
            }
            for name, (call, timeout) in cases.items():
                t0 = time.monotonic()
                try:
                    call(timeout)
                    code = "OK"
                except grpc.RpcError as e:
                    code = e.code().name
                t_deadline = t0 + timeout
                while srv.service.slots.free_compute() == 0 and time.monotonic() < t_deadline + 60:
                    time.sleep(0.005)
                released = time.monotonic()
                out[name] = {
                    "timeout_s": timeout,
                    "client_saw": code,
                    "release_after_deadline_s": released - t_deadline,
                }
    finally:
        srv.stop(0)
    return out


def peak_rss(models: Path, cam: pb.Camera, texts: tuple[str, ...]) -> dict[str, dict]:
    """Peak RSS above the warmed-up baseline for the worst request of each kind, each in a fresh server
    (no heap left over from an earlier request), with the estimate the working-memory budget reserves."""
    from fmgs.scene.manifest import Manifest

    out = {}
    big = camera(cam, MAX_W, MAX_H)
    manifest = Manifest.read(models / "demo")  # the estimates count the scene's Gaussians
    gaussians, embedded, dim = manifest.num_gaussians, manifest.num_selected, manifest.dim
    pts = np.random.default_rng(2).uniform(-1, 1, size=(1_000_000, 3)).astype(np.float32)
    many = [f"{t} {i}" for i in range(11) for t in texts][:64]
    classes = [f"{x} {i}" for i in range(3) for x in texts][:16]
    outputs = ("relevancy", "rgb", "depth", "alpha")
    cases = {
        f"Render {MAX_W}x{MAX_H}, 4 outputs, float32": (
            lambda s: list(
                s.Render(pb.RenderRequest(scene="demo", camera=big, text="red cube", outputs=ALL_OUTPUTS))
            ),
            budget.render_bytes(MAX_W, MAX_H, outputs, False, gaussians),
        ),
        f"Render {MAX_W}x{MAX_H}, 4 outputs, PNG": (
            lambda s: list(
                s.Render(
                    pb.RenderRequest(
                        scene="demo",
                        camera=big,
                        text="red cube",
                        outputs=ALL_OUTPUTS,
                        encoding=pb.IMAGE_ENCODING_PNG,
                    )
                )
            ),
            budget.render_bytes(MAX_W, MAX_H, outputs, True, gaussians),
        ),
        "PointQuery 1M points x 8 texts (61 MiB answer)": (
            lambda s: s.PointQuery(
                pb.PointQueryRequest(scene="demo", texts=list(texts[:1]) * 8, points=to_tensor(pts))
            ),
            budget.point_bytes(1_000_000, 8, ServerConfig().point_chunk),
        ),
        "TextQuery 64 texts, every Gaussian, all fields, instances": (
            lambda s: list(
                s.TextQuery(
                    pb.TextQueryRequest(
                        scene="demo",
                        texts=many,
                        top_k=1_000_000,
                        fields=list(range(1, 8)),
                        instances=pb.InstanceOptions(enabled=True),
                    )
                )
            ),
            budget.text_bytes(embedded, 64, 3 * 7, embedded, dim),  # as the server reserves
        ),
        f"Segment {MAX_W}x{MAX_H}, 16 classes, per Gaussian": (
            lambda s: list(
                s.Segment(pb.SegmentRequest(scene="demo", class_names=classes, camera=big, per_gaussian=True))
            ),
            budget.segment_bytes(MAX_W, MAX_H, 16, embedded),
        ),
    }
    for name, (call, estimate) in cases.items():
        with subprocess_server(models, "--preload") as (p, address):
            with grpc.insecure_channel(address, options=CLIENT_OPTIONS) as ch:
                base = memory(p.pid)[0]
                reset_peak(p.pid)
                t0 = time.perf_counter()
                try:
                    call(pb_grpc.FmgsStub(ch))
                    code = "OK"
                except grpc.RpcError as e:
                    code = e.code().name
                out[name] = {
                    "client_saw": code,
                    "seconds": time.perf_counter() - t0,
                    "baseline_mib": base / 2**20,
                    "peak_above_baseline_mib": (memory(p.pid)[1] - base) / 2**20,
                    "estimate_mib": estimate / 2**20,
                }
    out["_budget_mib"] = ServerConfig().work_memory_bytes / 2**20
    return out


def measure(models: Path, cam: pb.Camera, texts: tuple[str, ...]) -> dict:
    return {
        "grace_s": GRACE_S,
        "stop_margin_s": STOP_MARGIN_S,
        "shutdown_s": shutdowns(models, cam),
        "slot_release": slot_releases(models, cam, texts),
        "peak_rss": peak_rss(models, cam, texts),
    }


def markdown(h: dict) -> list[str]:
    bound = h["grace_s"] + h["stop_margin_s"]
    L = [
        "## Hostile load",
        "",
        f"Shutdown: SIGTERM to process exit, `fmgs-server --grace-s {h['grace_s']:.0f} --preload` (bound: "
        f"grace + {h['stop_margin_s']:.0f} s = {bound:.0f} s; before this pass, garbage on a pose stream "
        "hung the server until SIGKILL).",
        "",
        "| in flight at SIGTERM | seconds to exit | bounded |",
        "|---|---:|---|",
    ]
    for name, s in h["shutdown_s"].items():
        L.append(f"| {name} | {s:.2f} | {'yes' if s <= bound else '**no**'} |")
    L += [
        "",
        "Deadlines: one compute slot (`workers=1`); the client's timeout; seconds from its deadline until",
        "the server's slot was free again (target: within 0.5 s).",
        "",
        "| call | timeout | client saw | slot free after the deadline | within 0.5 s |",
        "|---|---:|---|---:|---|",
    ]
    for name, r in h["slot_release"].items():
        d = r["release_after_deadline_s"]
        ok = "yes" if d <= 0.5 else "**no**"
        L.append(f"| {name} | {r['timeout_s']:.1f} s | {r['client_saw']} | {d:+.2f} s | {ok} |")
    pr = {k: v for k, v in h["peak_rss"].items() if not k.startswith("_")}
    budget_mib = h["peak_rss"]["_budget_mib"]
    L += [
        "",
        "Memory: peak RSS above the warmed-up server's RSS for the worst request of each kind the limits "
        "allow (`/proc/PID/status` VmHWM after a reset), against the estimate the working-memory budget "
        f"reserves for it and the budget (`work_memory_bytes`, {budget_mib:.0f} MiB).",
        "",
        "| request | client saw | seconds | peak above baseline MiB | reserved MiB | under the budget |",
        "|---|---|---:|---:|---:|---|",
    ]
    for name, r in pr.items():
        ok = "yes" if r["peak_above_baseline_mib"] <= budget_mib else "**no**"
        L.append(
            f"| {name} | {r['client_saw']} | {r['seconds']:.1f} | {r['peak_above_baseline_mib']:.0f} | "
            f"{r['estimate_mib']:.0f} | {ok} |"
        )
    return [*L, ""]
