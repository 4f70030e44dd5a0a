"""Cluster failures as clients meet them: a scene replica and then Serve's gRPC proxy killed under load.

    python -m benchmarks.faults            # 2 scene replicas, ~90 s bounded
    python -m benchmarks.faults --quick    # shorter phases (a smoke run)

The demo scene (models/demo, its MiniLM text encoder) served by ``fmgs serve`` and by the Ray deployment
(``fmgs-server --ray``'s code path, a local Ray cluster, two scene replicas) from one repository, in one
run, loopback only. Closed-loop clients (the thin client ``FmgsClient`` with its default retry policy)
send text queries and renders through the Ray proxy; at ``--kill-replica-at`` the replica that answered
the last call is killed, at ``--kill-proxy-at`` the gRPC proxy. Records every call (start, end, status,
details), the second the proxy listens again and the first answer after it, then compares answers to
the direct server's. Writes CLUSTER_FAULTS.json and the failures section of CLUSTER.md (or --out).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import re
import shutil
import socket
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np

from benchmarks.common import RESULTS, machine, machine_words

ROOT = Path(__file__).resolve().parents[1]
TEXTS = ["red cube", "blue ball", "something to sit on", "a laptop"]
INTERNALS = re.compile(
    r"\x1b\[|\b\d{1,3}(\.\d{1,3}){3}\b|0x[0-9a-f]{6,}|\bpid\b|ActorID|actor_id|Traceback", re.I
)
"""What Ray's own exception text carries (colour codes, addresses, ids, reprs): never in a client's view."""
SECTION = "## Failures under load"


def _camera():
    from fmgs_client import CameraSpec

    return CameraSpec.look_at(eye=(2.2, -2.2, 1.6), target=(0.0, 0.0, 0.3), width=96, height=72)


def _answer(client, kind: str, i: int):
    """One call; returns what the comparison needs (indices and relevancies, or the relevancy image)."""
    text = TEXTS[i % len(TEXTS)]
    if kind == "query":
        [a] = client.query("demo", text, top_k=50)
        return ("query", text), (a.index.copy(), a.relevancy.copy())
    r = client.render("demo", _camera(), text)
    return ("render", text), (r.relevancy.copy(),)


def _same(a, b) -> bool:
    return len(a) == len(b) and all(
        x.shape == y.shape
        and (np.array_equal(x, y) if x.dtype.kind in "iu" else np.allclose(x, y, atol=1e-5))
        for x, y in zip(a, b, strict=True)
    )


class Load:
    """Closed-loop clients; every call recorded as (start s, end s, kind, code, details, answer key, ok)."""

    def __init__(self, address: str, reference: dict, clients: int) -> None:
        self.address, self.reference, self.clients = address, reference, clients
        self.calls: list[tuple] = []
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.t0 = time.monotonic()
        self.threads = [threading.Thread(target=self._run, args=(k,), daemon=True) for k in range(clients)]

    def start(self) -> None:
        self.t0 = time.monotonic()
        for t in self.threads:
            t.start()

    def _run(self, k: int) -> None:
        from fmgs_client import FmgsClient, FmgsError

        kind = "render" if k % 3 == 2 else "query"
        with FmgsClient(self.address, timeout=10.0) as c:
            i = k
            while not self.stop.is_set():
                s = time.monotonic() - self.t0
                try:
                    key, ans = _answer(c, kind, i)
                    code, details, right = "OK", "", _same(ans, self.reference[key])
                except FmgsError as e:
                    code, details, right = e.code, e.details, False
                except Exception as e:  # a client bug: recorded, never a dead load thread
                    code, details, right = "CLIENT_EXCEPTION", f"{type(e).__name__}: {e}"[:300], False
                with self.lock:
                    self.calls.append((s, time.monotonic() - self.t0, kind, code, details, right))
                i += 1

    def finish(self) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(30)


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def _replica_actor(address: str):
    """The Ray actor of the scene replica that answers a GetScene of the demo scene now."""
    import grpc
    import ray
    from ray import serve

    from fmgs_server.cluster.app import REPLICA_KEY
    from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
    from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc

    with grpc.insecure_channel(address) as ch:
        _, call = pb_grpc.FmgsStub(ch).GetScene.with_call(pb.SceneRequest(scene="demo"), timeout=30)
        replica = dict(call.trailing_metadata())[REPLICA_KEY]
    details = serve.context._get_global_client().get_serve_details()
    for r in details["applications"]["fmgs"]["deployments"]["SceneHost"]["replicas"]:
        if r["replica_id"] == replica:
            return ray.get_actor(r["actor_name"], namespace="serve"), replica
    raise RuntimeError(f"replica {replica} not among the deployment's replicas")


def _proxy_actor():
    import ray
    from ray import serve

    details = serve.context._get_global_client().get_serve_details()
    [proxy] = details["proxies"].values()
    return ray.get_actor(proxy["actor_name"], namespace="serve")


def per_second(calls: list[tuple], until: float) -> list[dict]:
    """Calls ended in each second: OK (right answer), OK but different, failed by status."""
    rows = []
    for sec in range(int(until) + 1):
        ended = [c for c in calls if sec <= c[1] < sec + 1]
        row = {"second": sec, "ok": sum(1 for c in ended if c[3] == "OK" and c[5])}
        row["wrong"] = sum(1 for c in ended if c[3] == "OK" and not c[5])
        row["failed"] = dict(Counter(c[3] for c in ended if c[3] != "OK"))
        rows.append(row)
    return rows


def run(quick: bool) -> dict:
    import ray
    from ray import serve

    from fmgs_client import FmgsClient
    from fmgs_server.cluster.config import ClusterConfig
    from fmgs_server.cluster.launch import set_proxy_health_env, start_ray_serve
    from fmgs_server.config import ServerConfig
    from fmgs_server.server import start_server

    kill_replica_at, kill_proxy_at, cap = (5.0, 15.0, 70.0) if quick else (10.0, 30.0, 110.0)
    res: dict = {"date": dt.date.today().isoformat(), "machine": machine(), "quick": quick}
    res.update(ray=ray.__version__, kill_replica_at=kill_replica_at, kill_proxy_at=kill_proxy_at)
    with tempfile.TemporaryDirectory() as tmp:
        models = Path(tmp) / "models"
        shutil.copytree(ROOT / "models" / "demo", models / "demo")
        cfg = ServerConfig(models=models, port=0, workers=1, reload_check_s=0.0)
        direct = start_server(cfg)  # the scene's own text encoder, loaded as users' servers load it
        reference = {}
        with FmgsClient(direct.address, timeout=60) as c:
            for kind in ("query", "render"):
                for i in range(len(TEXTS)):
                    key, ans = _answer(c, kind, i)
                    reference[key] = ans
        cc = ClusterConfig(min_replicas=2, max_replicas=2, replica_cpus=0.5, max_ongoing_requests=8)
        res["cluster"] = {"scene_replicas": 2, "ingress_replicas": cc.ingress_replicas, "read_attempts": 3}
        set_proxy_health_env()  # read by Serve's controller, which ray.init starts
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        load = None
        try:
            port = start_ray_serve(cfg, cc, None)
            addr = f"127.0.0.1:{port}"
            with FmgsClient(addr, timeout=120) as c:  # both replicas hold the scene before the clock starts
                for i in range(8):
                    _answer(c, "query", i)
            load = Load(addr, reference, clients=3)
            load.start()
            clock = lambda: time.monotonic() - load.t0  # noqa: E731
            while clock() < kill_replica_at:
                time.sleep(0.05)
            actor, replica = _replica_actor(addr)
            res["killed_replica"] = replica
            res["replica_killed_s"] = clock()
            ray.kill(actor, no_restart=True)
            print(f"{clock():.1f} s: killed scene replica {replica}", flush=True)
            while clock() < kill_proxy_at:
                time.sleep(0.05)
            proxy = _proxy_actor()
            ray.kill(proxy, no_restart=True)
            res["proxy_killed_s"] = clock()
            print(f"{clock():.1f} s: killed the gRPC proxy", flush=True)
            while _listening(port) and clock() < cap:  # the old process lets go of the port
                time.sleep(0.05)
            res["proxy_closed_s"] = clock()
            while not _listening(port) and clock() < cap:
                time.sleep(0.1)
            res["proxy_listening_s"] = clock() if _listening(port) else None
            print(f"{clock():.1f} s: proxy listening again", flush=True)
            after = res["proxy_listening_s"] or cap
            while clock() < min(cap, after + 10.0):
                time.sleep(0.1)
        finally:
            if load is not None:
                load.finish()
        res["duration_s"] = time.monotonic() - load.t0
        calls = sorted(load.calls)
        res["calls"] = len(calls)
        after = res["proxy_listening_s"]
        first_ok = next(
            (c[1] for c in calls if c[3] == "OK" and c[5] and after and c[0] >= after - 1e-9), None
        )
        # The first call that started after the proxy listened again and answered right.
        res["first_ok_after_listen_s"] = None if first_ok is None or after is None else first_ok - after
        res["per_second"] = per_second(calls, res["duration_s"])
        res["statuses"] = dict(Counter(f"{c[3]}: {c[4]}" if c[3] != "OK" else "OK" for c in calls))
        res["wrong_answers"] = sum(1 for c in calls if c[3] == "OK" and not c[5])
        # gRPC's own connect errors name the address the client dialled: that one is the client's.
        res["leaks"] = sorted({c[4] for c in calls if INTERNALS.search(c[4].replace(addr, "ADDRESS"))})
        k = res["replica_killed_s"]
        window = [c for c in calls if c[0] <= k + 0.5 and c[1] >= k and c[3] != "OK"]
        res["replica_failed_calls"] = {
            "n": len(window),
            "codes": dict(Counter(c[3] for c in window)),
            "in_flight_at_kill": sum(1 for c in calls if c[0] <= k <= c[1]),
            # The longest call among those in flight at the kill or started in the 2 s after it.
            "longest_call_s": max((c[1] - c[0] for c in calls if c[0] <= k + 2.0 and c[1] >= k), default=0.0),
        }
        # Answers after recovery, every text and kind, against the direct server's.
        with FmgsClient(addr, timeout=60) as c:
            same = 0
            for kind in ("query", "render"):
                for i in range(len(TEXTS)):
                    key, ans = _answer(c, kind, i)
                    same += _same(ans, reference[key])
        res["after_recovery_equal"] = f"{same}/{2 * len(TEXTS)}"
        direct.stop(0)
        serve.shutdown()
        ray.shutdown()
    return res


def section(res: dict) -> str:
    """The failures section of CLUSTER.md."""
    r = res["replica_failed_calls"]
    listen = res["proxy_listening_s"]
    first = res["first_ok_after_listen_s"]
    lines = [
        SECTION,
        "",
        f"Measured {res['date']} on {machine_words(res['machine'])}, one run of `python -m benchmarks.faults"
        f"{' --quick' if res['quick'] else ''}`: the demo scene on a local Ray cluster (ray {res['ray']}, "
        "2 scene replicas, 1 ingress), 3 closed-loop thin clients (2 querying, 1 rendering, default retry "
        "policy: 4 tries of a read on UNAVAILABLE, reconnect back-off capped at 1 s) through the gRPC proxy, "
        "loopback only.",
        f"At {res['replica_killed_s']:.1f} s the scene replica that answered the last call was killed; at "
        f"{res['proxy_killed_s']:.1f} s the gRPC proxy.",
        "",
        f"- Replica killed: {r['in_flight_at_kill']} calls in flight; calls failed around it: {r['n']} "
        f"({', '.join(f'{k} {v}' for k, v in r['codes'].items()) or 'none'}); the ingress tries reads "
        f"again on the other replica; the longest call around the kill took {r['longest_call_s']:.1f} s.",
        f"- Proxy killed at {res['proxy_killed_s']:.1f} s, listening again at "
        + (f"{listen:.1f} s" if listen is not None else "never (within the run)")
        + "; first right answer of a call started after that: "
        + (f"{first:.2f} s later." if first is not None else "none."),
        f"- Answers that came back OK but differed from the direct server's: {res['wrong_answers']} of "
        f"{res['calls']} calls; after recovery {res['after_recovery_equal']} answers (4 texts, query and "
        "render) equal the direct server's.",
        "- Client-visible texts with Ray internals (addresses, ids, reprs, colour codes): "
        f"{len(res['leaks'])}.",
        "",
        "| status | calls |",
        "|---|---|",
        *[f"| {k} | {v} |" for k, v in sorted(res["statuses"].items(), key=lambda kv: -kv[1])],
        "",
        "Calls ended per second (OK: the right answer):",
        "",
        "| second | OK | failed |",
        "|---|---|---|",
    ]
    marks = {int(res["replica_killed_s"]): " (replica killed)", int(res["proxy_killed_s"]): " (proxy killed)"}
    if listen is not None:
        marks[int(listen)] = marks.get(int(listen), "") + " (proxy listening)"
    for first, last, ok, wrong, failed in _runs(res["per_second"], marks):
        span = f"{first}" if first == last else f"{first}-{last}"
        bad = ", ".join(f"{k} {v}" for k, v in failed.items())
        wrong_s = f", wrong {wrong}" if wrong else ""
        lines.append(f"| {span}{marks.get(first, '')} | {ok}{wrong_s} | {bad} |")
    lines.append("")
    return "\n".join(lines)


def _runs(rows: list[dict], marks: dict[int, str]):
    """Rows merged into spans of seconds with no right answer and the same failing codes (an outage
    reads as one line), sums kept; marked seconds stand alone."""
    out: list[list] = []
    for row in rows:
        sec, quiet = row["second"], row["ok"] == 0 and row["wrong"] == 0
        prev = out[-1] if out else None
        joins = prev is not None and prev[1] == sec - 1 and sec not in marks
        if joins and quiet and prev[2] == 0 and prev[3] == 0 and set(prev[4]) == set(row["failed"]):
            prev[1] = sec
            for k, v in row["failed"].items():
                prev[4][k] += v
            continue
        out.append([sec, sec, row["ok"], row["wrong"], dict(row["failed"])])
    return [tuple(r) for r in out]


def write_section(path: Path, text: str) -> None:
    """Put ``text`` in CLUSTER.md in place of an earlier failures section (or at its end)."""
    old = path.read_text() if path.exists() else ""
    head = old.split(SECTION, 1)[0].rstrip("\n")
    path.write_text((head + "\n\n" if head else "") + text)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=str(RESULTS))
    a = ap.parse_args()
    res = run(a.quick)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "CLUSTER_FAULTS.json").write_text(json.dumps(res, indent=1, default=str))
    text = section(res)
    write_section(out / "CLUSTER.md", text)
    print(text)
    ok = (
        not res["leaks"]
        and res["wrong_answers"] == 0
        and res["after_recovery_equal"] == f"{2 * len(TEXTS)}/{2 * len(TEXTS)}"
        and res["first_ok_after_listen_s"] is not None
    )
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
