"""Serving on Ray: the proxy's per-request overhead, throughput against replicas, sharded text queries.

    python -m benchmarks.cluster            # 1M-Gaussian scene, shards 1/2/4/8, 1 and 2 replicas
    python -m benchmarks.cluster --quick    # 100K Gaussians, fewer calls (a smoke run)

Everything goes through gRPC from a client in this process: ``fmgs serve`` (in-process server) and the
Ray deployment (``fmgs_server.cluster``, a local Ray cluster) on the same repository, in one run.
Scenes are field-like (benchmarks/common.py); queries are the "typical" (best cosine ~0.85) and "clip"
(best cosine 0.2-0.35) sets of benchmarks/query_sets.py. Writes CLUSTER.md and CLUSTER.json (or --out)
with a capacity model computed from the measured figures.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

import torch

from benchmarks.common import (
    RESULTS,
    D,
    TableEncoder,
    canonical_vectors,
    export,
    fieldlike,
    gaussians_from,
    machine,
    proto_camera,
)
from benchmarks.query_sets import query_sets
from benchmarks.scenes import synthetic


def pct(xs, q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, round(q * (len(xs) - 1)))] * 1e3


def stats(ts) -> dict:
    return {"p50_ms": pct(ts, 0.5), "p90_ms": pct(ts, 0.9), "p99_ms": pct(ts, 0.99), "n": len(ts)}


def build_repo(root: Path, n: int, shards: list[int], n_queries: int):
    """A repository with a small scene, an n-Gaussian scene and its shardings; the text encoder."""
    from fmgs.scene.shards import write_shards

    canon = canonical_vectors()
    texts = {}
    for name, size in (("small", 50_000), ("big", n)):
        s = synthetic(size, seed=3)
        emb = fieldlike(s.means)
        export(root / name, gaussians_from(s), emb, canon)
        if name == "big":
            sets = query_sets(emb.half().float(), torch.zeros(0, dtype=torch.int64), n_queries)
            texts = {k: sets[k] for k in ("typical", "clip")}
        del emb
    t_shard = {}
    for k in shards:
        t0 = time.perf_counter()
        write_shards(root / "big", root / f"big-{k}shards", k)
        t_shard[k] = time.perf_counter() - t0
    queries = torch.cat(list(texts.values()))
    enc = TableEncoder(queries, canon)
    names = {k: [f"q{i + j * n_queries}" for i in range(n_queries)] for j, k in enumerate(texts)}
    return enc, names, t_shard


def call_times(stub, method: str, reqs, md=()) -> list[float]:
    out = []
    for r in reqs:
        t0 = time.perf_counter()
        res = getattr(stub, method)(r, timeout=300, metadata=md)
        if not hasattr(res, "SerializeToString"):
            res = list(res)
        out.append(time.perf_counter() - t0)
        assert res is not None
    return out


def overhead(direct: str, ray_addr: str, names, reps: int, n: int) -> dict:
    """The same calls, interleaved, on fmgs serve and through the Ray proxy."""
    import grpc

    from fmgs.cameras import Camera
    from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
    from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc

    K = torch.tensor([[100.0, 0, 64], [0, 100.0, 48], [0, 0, 1]], dtype=torch.float64)
    V = torch.eye(4, dtype=torch.float64)
    cam = proto_camera(Camera(K, V, 128, 96))
    q = names["typical"][0]
    kinds = {
        "GetScene": ("GetScene", pb.SceneRequest(scene="small")),
        "TextQuery small top-100": ("TextQuery", pb.TextQueryRequest(scene="small", texts=[q], top_k=100)),
        f"TextQuery {n:,} top-100": ("TextQuery", pb.TextQueryRequest(scene="big", texts=[q], top_k=100)),
        "Render 128x96 relevancy": (
            "Render",
            pb.RenderRequest(scene="small", camera=cam, text=q, outputs=[pb.RENDER_OUTPUT_RELEVANCY]),
        ),
    }
    stubs = {
        k: pb_grpc.FmgsStub(grpc.insecure_channel(a)) for k, a in (("direct", direct), ("ray", ray_addr))
    }
    res = {}
    for label, (method, req) in kinds.items():
        for s in stubs.values():
            call_times(s, method, [req] * 3)  # warm: loads, compiles, caches the scene on a replica
        t = {"direct": [], "ray": []}
        for _ in range(reps):
            for k, s in stubs.items():
                t[k] += call_times(s, method, [req])
        res[label] = {k: stats(v) for k, v in t.items()}
        res[label]["added_p50_ms"] = res[label]["ray"]["p50_ms"] - res[label]["direct"]["p50_ms"]
    return res


def load(address: str, scene: str, texts: list[str], clients: int, seconds: float) -> dict:
    """``clients`` closed-loop clients sending one-text queries for ``seconds``."""
    import grpc

    from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
    from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc

    lat: list[float] = []
    errors = [0]
    end = time.monotonic() + seconds
    lock = threading.Lock()

    def client(c: int) -> None:
        stub = pb_grpc.FmgsStub(grpc.insecure_channel(address))
        i = c
        while time.monotonic() < end:
            req = pb.TextQueryRequest(scene=scene, texts=[texts[i % len(texts)]], top_k=100)
            t0 = time.perf_counter()
            try:
                list(stub.TextQuery(req, timeout=120))
                with lock:
                    lat.append(time.perf_counter() - t0)
            except grpc.RpcError:
                with lock:
                    errors[0] += 1
            i += clients

    threads = [threading.Thread(target=client, args=(c,)) for c in range(clients)]
    t0 = time.monotonic()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.monotonic() - t0
    return {**stats(lat), "qps": len(lat) / wall, "errors": errors[0], "clients": clients}


def sharded(ray_addr: str, names, shards: list[int], reps: int) -> dict:
    import grpc

    from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
    from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc

    stub = pb_grpc.FmgsStub(grpc.insecure_channel(ray_addr))
    res = {}
    for k in shards:
        scene = "big" if k == 1 else f"big-{k}shards"
        res[k] = {}
        for kind, texts in names.items():
            reqs = [pb.TextQueryRequest(scene=scene, texts=[t], top_k=100) for t in texts[:reps]]
            call_times(stub, "TextQuery", reqs[:2])  # warm: the shards load on their replicas
            res[k][kind] = stats(call_times(stub, "TextQuery", reqs))
    return res


def capacity(res: dict) -> dict:
    """Nodes for the two workloads of the issue, from the measured per-replica figures."""
    per = res["resident_bytes_1m"]
    q = res["load"]["ray_1"]  # one replica, one CPU: its closed-loop throughput
    qps_per_cpu = q["qps"]
    clip_ms = res["sharded"]["1"]["clip"]["p50_ms"]
    typ_ms = res["sharded"]["1"]["typical"]["p50_ms"]
    node_mem, node_cpus = 64 * 2**30, 16
    # (a) 1,000 scenes of 1M Gaussians, 500 robots x 2 queries/s = 1,000 queries/s
    mem_nodes = 1000 * per / (0.75 * node_mem)
    cpu_nodes = 1000 / (qps_per_cpu * node_cpus)
    # CLIP-like queries cost more than the typical ones the load ran with: scale by their latencies.
    cpu_nodes_clip = cpu_nodes * clip_ms / typ_ms
    a = {
        "scenes": 1000,
        "qps": 1000,
        "resident_gib_total": 1000 * per / 2**30,
        "nodes_for_memory": mem_nodes,
        "nodes_for_compute": cpu_nodes,
        "nodes_for_compute_clip": cpu_nodes_clip,
        "nodes": max(1, int(-(-max(mem_nodes, cpu_nodes) // 1))),
        "nodes_clip": max(1, int(-(-max(mem_nodes, cpu_nodes_clip) // 1))),
        "p50_ms": typ_ms,
        "p50_clip_ms": clip_ms,
    }
    # (b) one 10^8-Gaussian scene: 100 shards of 1M (one per replica-CPU); a query's latency is the
    # slowest shard plus the merge and the fan-out; its cost is 100 shard queries.
    shard_ms = {k: v["clip"]["p50_ms"] for k, v in res["sharded"].items()}
    b = {
        "gaussians": 10**8,
        "shards": 100,
        "resident_gib_total": 100 * per / 2**30,
        "nodes_for_memory": 100 * per / (0.75 * node_mem),
        "p50_ms_estimate": clip_ms + res["overhead"]["TextQuery small top-100"]["added_p50_ms"] * 2,
        "cpu_s_per_query": 100 * clip_ms / 1e3,
        "measured_clip_p50_by_shards_ms": shard_ms,
    }
    b["nodes_for_1_qps"] = b["cpu_s_per_query"] / node_cpus
    return {"node": {"memory_gib": 64, "cpus": node_cpus, "usable_memory": 0.75}, "a": a, "b": b}


def report(res: dict) -> str:
    m = res["machine"]
    lines = [
        "# Serving on Ray: overhead, replicas, shards",
        "",
        f"Measured {res['date']} on {m.get('cpu', '?')} ({m.get('cores', '?')} cores), one run of "
        f"`python -m benchmarks.cluster{' --quick' if res['quick'] else ''}`. A local Ray cluster "
        f"(ray {res['ray']}) on this machine; every call through gRPC from a client in the same process.",
        f"Scene: {res['gaussians']:,} field-like Gaussians, D={D}; top-100; queries 'typical' (best cosine "
        "~0.85) and 'clip' (0.2-0.35).",
        "",
        "## Per-request overhead of the Ray path (same calls interleaved, fmgs serve vs Ray Serve proxy)",
        "",
        "| call | direct p50 | direct p90 | Ray p50 | Ray p90 | added p50 |",
        "|---|---|---|---|---|---|",
    ]
    for k, v in res["overhead"].items():
        d, r = v["direct"], v["ray"]
        lines.append(
            f"| {k} | {d['p50_ms']:.1f} | {d['p90_ms']:.1f} | {r['p50_ms']:.1f} | {r['p90_ms']:.1f} | "
            f"{v['added_p50_ms']:+.1f} ms |"
        )
    lines += [
        "",
        f"## Throughput against replicas ({res['load_clients']} closed-loop clients, "
        f"{res['load_seconds']:.0f} s each, one-text queries on the {res['gaussians']:,}-Gaussian scene)",
        "",
        "| server | queries/s | p50 | p99 | errors |",
        "|---|---|---|---|---|",
    ]
    for k, v in res["load"].items():
        lines.append(
            f"| {k} | {v['qps']:.1f} | {v['p50_ms']:.0f} ms | {v['p99_ms']:.0f} ms | {v['errors']} |"
        )
    lines += [
        "",
        "This machine has 2 cores: the Ray processes (proxy, controller, ingress, replicas) and the client "
        "share them, so a second replica cannot add a core's worth here; the figures show the overhead "
        "and that replicas share the load, not the scaling a cluster of machines gives.",
        "",
        f"## Sharded text queries through Ray (one scene of {res['gaussians']:,} Gaussians, "
        f"{res['shard_replicas']} scene replicas)",
        "",
        "| shards | typical p50 | typical p90 | clip p50 | clip p90 | split time |",
        "|---|---|---|---|---|---|",
    ]
    for k, v in res["sharded"].items():
        t = res["shard_split_s"].get(k)
        ty, cl = v["typical"], v["clip"]
        split = "" if t is None else f"{t:.1f} s"
        lines.append(
            f"| {k} | {ty['p50_ms']:.0f} | {ty['p90_ms']:.0f} | {cl['p50_ms']:.0f} | {cl['p90_ms']:.0f} "
            f"| {split} |"
        )
    c = res["capacity"]
    a, b = c["a"], c["b"]
    lines += [
        "",
        "Answers are the same for every shard count (tests/query/test_sharded.py, "
        "tests/server/test_cluster.py: bit for bit). On 2 cores the shards' work is not parallel, so "
        "latency grows with the fan-out and the merge; 10M Gaussians were not measured here (memory "
        "and time); the model below scales from 1M.",
        "",
        "## Capacity model (from the measured figures above)",
        "",
        f"Node: {c['node']['cpus']} CPUs, {c['node']['memory_gib']} GiB, 75% of it for scenes. One "
        f"1M-Gaussian scene holds {res['resident_bytes_1m'] / 2**20:.0f} MiB resident (query state, "
        f"geometry, field); one replica-CPU answers {res['load']['ray_1']['qps']:.1f} one-text "
        "queries/s (measured, closed loop).",
        "",
        f"(a) 1,000 scenes of 1M Gaussians, 500 robots at 2 queries/s (1,000 queries/s): "
        f"{a['resident_gib_total']:.0f} GiB resident -> {a['nodes_for_memory']:.1f} nodes for memory; "
        f"1,000 typical queries/s -> {a['nodes_for_compute']:.1f} nodes for compute, **{a['nodes']} nodes**; "
        f"if every query is CLIP-like ({a['p50_clip_ms']:.0f} against {a['p50_ms']:.0f} ms each) "
        f"{a['nodes_for_compute_clip']:.1f} nodes for compute, **{a['nodes_clip']} nodes**. "
        f"Expected p50 {a['p50_ms']:.0f} ms for typical queries and {a['p50_clip_ms']:.0f} ms for CLIP-like "
        f"ones (one request at a time, above); p99 {res['load']['ray_1']['p99_ms']:.0f} ms as measured with "
        "4 requests in flight on one replica (the autoscaler aims at 2 per replica, so an upper figure).",
        "",
        f"(b) one 10^8-Gaussian scene as 100 shards of 1M: {b['resident_gib_total']:.0f} GiB resident -> "
        f"{b['nodes_for_memory']:.1f} nodes for memory; each query costs 100 shard queries "
        f"({b['cpu_s_per_query']:.1f} CPU-s for a CLIP-like one), so {b['nodes_for_1_qps']:.2f} nodes "
        "per query/s; "
        f"p50 ~{b['p50_ms_estimate']:.0f} ms when every shard has its own CPU (slowest shard + two hops).",
        "",
    ]
    return "\n".join(lines)


def keep_faults_section(out: Path) -> None:
    """CLUSTER.md carries the failures section of benchmarks.faults (from its CLUSTER_FAULTS.json)."""
    from benchmarks.faults import section, write_section

    faults = out / "CLUSTER_FAULTS.json"
    if faults.exists():
        write_section(out / "CLUSTER.md", section(json.loads(faults.read_text())))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=str(RESULTS))
    ap.add_argument("--gaussians", type=int)
    ap.add_argument("--report-only", metavar="JSON", help="rewrite CLUSTER.md from a CLUSTER.json")
    a = ap.parse_args()
    if a.report_only:
        res = json.loads(Path(a.report_only).read_text())
        res["capacity"] = capacity(res)
        Path(a.out, "CLUSTER.md").write_text(report(res))
        keep_faults_section(Path(a.out))
        Path(a.out, "CLUSTER.json").write_text(json.dumps(res, indent=1, default=str))
        return 0
    n = a.gaussians or (100_000 if a.quick else 1_000_000)
    shards = [1, 2, 4] if a.quick else [1, 2, 4, 8]
    reps = 10 if a.quick else 40
    seconds = 5.0 if a.quick else 20.0
    torch.set_num_threads(1)
    import ray
    from ray import serve

    from fmgs.query.engine import SceneEngine
    from fmgs_server.cluster.app import build_app
    from fmgs_server.cluster.config import ClusterConfig
    from fmgs_server.cluster.launch import start_ray_serve
    from fmgs_server.config import ServerConfig
    from fmgs_server.server import start_server

    res = {"date": dt.date.today().isoformat(), "machine": machine(), "quick": a.quick, "gaussians": n}
    res["ray"] = ray.__version__
    with tempfile.TemporaryDirectory() as tmp:
        models = Path(tmp) / "models"
        models.mkdir()
        print(f"building a {n:,}-Gaussian repository and its shardings...", flush=True)
        enc, names, split = build_repo(models, n, [k for k in shards if k > 1], reps)
        res["shard_split_s"] = {str(k): v for k, v in split.items()}
        res["resident_bytes_1m"] = SceneEngine.open(models / "big").nbytes() * 1_000_000 / n
        cfg = ServerConfig(models=models, port=0, workers=1, reload_check_s=0.0)
        direct = start_server(cfg, encoder_factory=lambda i: enc)
        try:
            cc = ClusterConfig(min_replicas=1, max_replicas=1, replica_cpus=1.0, max_ongoing_requests=8)
            ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
            port = start_ray_serve(cfg, cc, None, lambda i: enc)
            addr = f"127.0.0.1:{port}"
            print("overhead...", flush=True)
            res["overhead"] = overhead(direct.address, addr, names, reps, n)
            res["load_clients"], res["load_seconds"] = 4, seconds
            print("load, fmgs serve and one replica...", flush=True)
            texts = names["typical"]
            res["load"] = {"fmgs serve (1 worker)": load(direct.address, "big", texts, 4, seconds)}
            res["load"]["ray_1"] = load(addr, "big", texts, 4, seconds)
            cc2 = ClusterConfig(min_replicas=2, max_replicas=2, replica_cpus=0.5, max_ongoing_requests=8)
            serve.run(build_app(cfg, cc2, lambda i: enc), name=cc2.app_name, route_prefix="/fmgs")
            print("load, two replicas...", flush=True)
            load(addr, "big", texts, 4, 3.0)  # both replicas hold the scene
            res["load"]["ray_2"] = load(addr, "big", texts, 4, seconds)
            print("sharded...", flush=True)
            res["shard_replicas"] = 2
            res["sharded"] = {str(k): v for k, v in sharded(addr, names, shards, reps).items()}
        finally:
            direct.stop(0)
            serve.shutdown()
            ray.shutdown()
    res["capacity"] = capacity(res)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "CLUSTER.json").write_text(json.dumps(res, indent=1, default=str))
    (out / "CLUSTER.md").write_text(report(res))
    keep_faults_section(out)
    print(report(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
