"""Text queries through two checkouts of the code, side by side, on one package (a refactor's check).

    git worktree add /tmp/base REV                          # the code before
    python -m benchmarks.text_ab --base /tmp/base           # this checkout against it, 1M Gaussians
    python -m benchmarks.text_ab --base /tmp/base --quick   # 50K Gaussians (completion only)

One package is exported by this checkout (the scene and query sets of benchmarks/text.py); then each
round runs a fresh worker process per checkout, alternating which goes first, and each worker opens the
package with ``SceneEngine.open`` (the server's path, default config, one thread), pages it in and times
``text_query`` for every query set and K, and ``text_query_many`` for a batch of 8. Answers must be the
same rows in the same order from both checkouts (else exit 1). Writes STEM.md and STEM.json to --out.
"""

from __future__ import annotations

import argparse
import datetime as dt
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]  # not benchmarks.common: the worker imports nothing of ours
BATCH = ("typical", "clip")


def worker(pkg: Path, queries: Path, ks: list[int], out: Path) -> None:
    """Runs in a child whose PYTHONPATH is the checkout under test: only fmgs, torch, numpy, numba."""
    import numba
    import torch
    from safetensors.torch import load_file

    from fmgs.query.engine import EngineConfig, SceneEngine

    torch.set_num_threads(1)
    numba.set_num_threads(1)
    sets = load_file(str(queries))
    eng = SceneEngine.open(pkg, EngineConfig())
    for f in sorted(pkg.rglob("*")):  # the served steady state: the package in the page cache
        if f.is_file():
            with f.open("rb") as fh:
                while fh.read(1 << 24):
                    pass
    first = next(iter(sets.values()))[0]
    eng.text_query(first, 10)  # compile (or load) the kernels
    res: dict = {"ms": {}, "rows": {}}
    for name, qs in sets.items():
        for k in ks:
            key = f"{name}/k={k}"
            res["ms"][key], res["rows"][key] = [], []
            for q in qs:
                t0 = time.perf_counter()
                a = eng.text_query(q, k)
                res["ms"][key].append((time.perf_counter() - t0) * 1e3)
                res["rows"][key].append(hashlib.sha1(a.index.numpy().tobytes()).hexdigest())
    for name in BATCH:
        qs = sets[name][:8]
        key = f"batch8 {name}/k=100"
        res["ms"][key], res["rows"][key] = [], []
        for _ in range(3):
            t0 = time.perf_counter()
            many = eng.text_query_many(qs, 100)
            res["ms"][key].append((time.perf_counter() - t0) * 1e3)
        res["rows"][key] = [hashlib.sha1(a.index.numpy().tobytes()).hexdigest() for a in many]
    out.write_text(json.dumps(res))


def run_worker(checkout: Path, pkg: Path, queries: Path, ks: list[int], out: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(checkout)}
    # -P: the script's folder is not put on sys.path, so fmgs comes from the checkout under test.
    cmd = [sys.executable, "-P", str(Path(__file__).resolve()), "--worker", str(pkg), str(queries), str(out)]
    cmd += ["--ks", ",".join(map(str, ks))]
    subprocess.run(cmd, env=env, check=True, cwd=checkout)
    return json.loads(out.read_text())


def git_rev(checkout: Path) -> str:
    cmd = ["git", "-C", str(checkout), "rev-parse", "--short", "HEAD"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    return r.stdout.strip() or "unknown"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", type=Path, help="the checkout to compare against (required unless --worker)")
    ap.add_argument("--gaussians", type=int, default=1_000_000, help="scene size (default 1,000,000)")
    ap.add_argument("--queries", type=int, default=6, help="queries per set (default 6)")
    ap.add_argument("--rounds", type=int, default=4, help="worker pairs, alternating order (default 4)")
    ap.add_argument("--quick", action="store_true", help="50K Gaussians, 2 queries, 2 rounds")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results", help="report folder")
    ap.add_argument("--stem", default="TEXT_AB", help="report file names (STEM.md, STEM.json)")
    ap.add_argument("--worker", nargs=3, metavar=("PACKAGE", "QUERIES", "OUT"), help=argparse.SUPPRESS)
    ap.add_argument("--ks", default="1,100,10000", help=argparse.SUPPRESS)
    a = ap.parse_args()
    ks = [int(k) for k in a.ks.split(",")]
    if a.worker:
        worker(Path(a.worker[0]), Path(a.worker[1]), ks, Path(a.worker[2]))
        return 0
    if a.base is None:
        ap.error("--base CHECKOUT is required")
    if a.quick:
        a.gaussians, a.queries, a.rounds = 50_000, 2, 2
    return compare(a.base.resolve(), ROOT, a)


def compare(base: Path, head: Path, a: argparse.Namespace) -> int:
    from safetensors.torch import save_file

    from benchmarks.common import machine
    from benchmarks.query_sets import QUERY_SETS, query_sets
    from benchmarks.text import ks_for, package, stored

    ks = ks_for(a.gaussians)
    tmp = Path(tempfile.mkdtemp(prefix="text_ab_"))
    pkg, copies, export_s = package(tmp, a.gaussians)
    emb, _ = stored(pkg)
    sets = query_sets(emb, copies, max(a.queries, 8))
    qfile = tmp / "queries.safetensors"
    take = {n: 8 if n in BATCH else a.queries for n in QUERY_SETS}  # a batch needs 8 texts
    save_file({n: sets[n][: max(a.queries, take[n])].contiguous() for n in QUERY_SETS}, str(qfile))
    del emb
    runs: dict[str, list[dict]] = {"base": [], "head": []}
    for r in range(a.rounds):
        order = [("base", base), ("head", head)] if r % 2 == 0 else [("head", head), ("base", base)]
        for name, checkout in order:
            t0 = time.perf_counter()
            runs[name].append(run_worker(checkout, pkg, qfile, ks, tmp / f"{name}{r}.json"))
            print(f"round {r} {name}: {time.perf_counter() - t0:.1f} s", flush=True)
    same = all(x["rows"] == runs["base"][0]["rows"] for x in runs["base"] + runs["head"])
    table = {}
    for key in runs["base"][0]["ms"]:
        med = {n: statistics.median(statistics.median(x["ms"][key]) for x in runs[n]) for n in runs}
        spread = {n: (min(statistics.median(x["ms"][key]) for x in runs[n]),
                      max(statistics.median(x["ms"][key]) for x in runs[n])) for n in runs}  # fmt: skip
        table[key] = {"base_ms": med["base"], "head_ms": med["head"], "ratio": med["head"] / med["base"],
                      "base_range": spread["base"], "head_range": spread["head"]}  # fmt: skip
    res = {
        "machine": machine(),
        "date": dt.datetime.now().isoformat(timespec="seconds"),
        "base": git_rev(base),
        "head": git_rev(head),
        "gaussians": a.gaussians,
        "queries_per_set": a.queries,
        "rounds": a.rounds,
        "export_s": export_s,
        "same_answers": same,
        "table": table,
    }
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / f"{a.stem}.json").write_text(json.dumps(res, indent=1))
    (a.out / f"{a.stem}.md").write_text(report(res, a))
    print((a.out / f"{a.stem}.md").read_text())
    return 0 if same else 1


def report(res: dict, a: argparse.Namespace) -> str:
    m = res["machine"]
    lines = [
        "# Text queries before and after a change, side by side",
        "",
        f"Machine: {m['cpu']}, {m['cores']} cores, one thread; {res['date']}. Base {res['base']}, head "
        f"{res['head']}. {res['gaussians']:,} field-like Gaussians (benchmarks/text.py's scene), "
        f"{res['queries_per_set']} queries per set, {res['rounds']} rounds of one fresh process per "
        "checkout, alternating which goes first. Reproduce: `git worktree add /tmp/base "
        f"{res['base']}; python -m benchmarks.text_ab --base /tmp/base --rounds {res['rounds']}`.",
        "",
        "Same answers (rows and order, every query, both checkouts, every round): "
        f"**{res['same_answers']}**.",
        "",
        "Medians over rounds of each round's median over the set's queries (range of the round medians).",
        "",
        "| set / K | base ms | head ms | head / base |",
        "|---|---|---|---|",
    ]
    for key, t in res["table"].items():
        b, h = t["base_range"], t["head_range"]
        lines.append(
            f"| {key} | {t['base_ms']:.1f} ({b[0]:.1f}-{b[1]:.1f}) | "
            f"{t['head_ms']:.1f} ({h[0]:.1f}-{h[1]:.1f}) | {t['ratio']:.3f} |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
