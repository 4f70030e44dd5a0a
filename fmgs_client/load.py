"""A bounded load generator: N concurrent clients sending a mix of text queries and pose renders.

Bounded in requests and in time; reports latency percentiles, throughput and every status code seen.
"""

from __future__ import annotations

import math
import statistics
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import grpc

from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc


@dataclass(frozen=True)
class LoadConfig:
    """What the clients send."""

    scene: str
    """Scene to query."""
    texts: tuple[str, ...]
    """Texts used in turn by text queries and renders."""
    camera: pb.Camera | None = None
    """Camera of the pose renders (None: text queries only)."""
    clients: int = 32
    """Concurrent clients, each on its own channel."""
    requests: int = 320
    """Requests in total (split evenly over the clients)."""
    render_every: int = 4
    """Every n-th request of a client is a pose render (0: never)."""
    top_k: int = 100
    """top_k of the text queries."""
    timeout_s: float = 30.0
    """Deadline of each request."""
    max_seconds: float = 300.0
    """Stop sending after this long, whatever is left."""

    def __post_init__(self) -> None:
        if isinstance(self.texts, str) or not self.texts or not all(isinstance(t, str) for t in self.texts):
            raise ValueError(f"texts: need one or more strings, got {self.texts!r}")
        for name in ("clients", "requests", "render_every", "top_k"):
            low = 1 if name == "clients" else 0
            if getattr(self, name) < low:
                raise ValueError(f"{name} must be >= {low}, got {getattr(self, name)}")
        for name in ("timeout_s", "max_seconds"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number of seconds, got {v}")


@dataclass
class LoadReport:
    """What the run saw."""

    sent: int = 0
    ok: int = 0
    codes: Counter = field(default_factory=Counter)
    """Status code name -> count, OK included."""
    latencies_ms: list[float] = field(default_factory=list)
    """Latency of each OK request."""
    seconds: float = 0.0

    @property
    def errors(self) -> int:
        return self.sent - self.ok

    def percentile(self, p: float) -> float | None:
        """The p-th percentile (0-100, nearest rank) of the OK requests' latencies in ms; None when no
        request succeeded (a number would be made up, and NaN is not JSON)."""
        if not 0 <= p <= 100:
            raise ValueError(f"percentile must lie in [0, 100], got {p}")
        if not self.latencies_ms:
            return None
        xs = sorted(self.latencies_ms)
        return xs[min(len(xs) - 1, round(p / 100 * (len(xs) - 1)))]

    @property
    def throughput(self) -> float:
        return self.ok / self.seconds if self.seconds > 0 else 0.0

    def summary(self) -> str:
        if self.latencies_ms:
            med = statistics.median(self.latencies_ms)
            lat = f"p50 {med:.1f} ms, p99 {self.percentile(99):.1f} ms"
        else:
            lat = "no latencies (no request OK)"
        return (
            f"{self.sent} requests in {self.seconds:.1f} s: {self.ok} OK ({self.throughput:.1f}/s), "
            f"{lat}; codes {dict(self.codes)}"
        )


def run_load(
    address: str,
    cfg: LoadConfig,
    channel_factory: Callable[[str], grpc.Channel] = grpc.insecure_channel,
    metadata: tuple[tuple[str, str], ...] = (),
) -> LoadReport:
    """Drive ``cfg.clients`` concurrent clients against ``address`` until the requests or the time run out."""
    rep = LoadReport()
    lock = threading.Lock()
    per = [
        cfg.requests // cfg.clients + (1 if i < cfg.requests % cfg.clients else 0) for i in range(cfg.clients)
    ]
    t_end = time.monotonic() + cfg.max_seconds
    start = threading.Barrier(cfg.clients + 1)

    def client(k: int) -> None:
        with channel_factory(address) as ch:
            stub = pb_grpc.FmgsStub(ch)
            start.wait()
            for i in range(per[k]):
                if time.monotonic() > t_end:
                    return
                text = cfg.texts[(k + i) % len(cfg.texts)]
                render = (
                    cfg.camera is not None
                    and cfg.render_every
                    and i % cfg.render_every == cfg.render_every - 1
                )
                t0 = time.perf_counter()
                try:
                    if render:
                        req = pb.RenderRequest(scene=cfg.scene, camera=cfg.camera, text=text, sequence=i)
                        list(stub.Render(req, timeout=cfg.timeout_s, metadata=metadata))
                    else:
                        req = pb.TextQueryRequest(scene=cfg.scene, texts=[text], top_k=cfg.top_k)
                        list(stub.TextQuery(req, timeout=cfg.timeout_s, metadata=metadata))
                    code = "OK"
                except grpc.RpcError as e:
                    code = e.code().name
                ms = (time.perf_counter() - t0) * 1e3
                with lock:
                    rep.sent += 1
                    rep.codes[code] += 1
                    if code == "OK":
                        rep.ok += 1
                        rep.latencies_ms.append(ms)

    threads = [threading.Thread(target=client, args=(k,), daemon=True) for k in range(cfg.clients)]
    for t in threads:
        t.start()
    start.wait()
    t0 = time.perf_counter()
    for t in threads:
        t.join()
    rep.seconds = time.perf_counter() - t0
    return rep
