"""Text queries on a large scene, every query set, against faiss on the same embeddings and thread count.

    pip install faiss-cpu               # benchmark-only dependency
    python -m benchmarks.text           # 1M Gaussians, D=512, 12 queries per set, one thread
    python -m benchmarks.text --quick   # 50K Gaussians, 3 queries per set (completion only)

Writes benchmarks/results/TEXT.md and TEXT.json (or --out DIR). The scene is field-like with clone ties
(benchmarks/query_sets.py), exported as a package; ours is the engine as the server runs it
(SceneEngine.open, compact default, text_query). faiss indexes the same float16 embeddings with the
margin trick (x' = [f, -max_n f.c_n], q' = [q, 1]) so its inner product is our ranking's margin:
IndexFlatIP (exact float32) and IVF1024,SQ8 with float16 refinement of 1,000 candidates, nprobe 64
(benchmarks/faiss_peer.py, the peers of every text report).
Recall is the fraction of the K answers whose float64 margin reaches the exact K-th margin (tie-aware:
another copy of a tied row counts); ours is also checked equal to the brute force, rows and order.
"""

from __future__ import annotations

import argparse
import datetime as dt
import gc
import json
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import RESULTS, D, machine, page_in, rss_gb
from benchmarks.faiss_peer import IVF, build, margins, recall, timed_search, top_of
from benchmarks.query_sets import QUERY_SETS, query_sets, scene_embeddings
from fmgs.gaussians import GaussianSet
from fmgs.query.engine import EngineConfig, SceneEngine
from fmgs.query.plan import choose_first_pass, first_pass_upper, first_rescore_count
from fmgs.scene.package import export_scene
from fmgs.vecmath import safe_normalize


def one_thread() -> None:
    import numba

    torch.set_num_threads(1)
    numba.set_num_threads(1)


def package(folder: Path, n: int) -> tuple[Path, torch.Tensor, float]:
    """The scene exported as a package; returns it, the rows that are copies, and the export time. The
    embeddings are made in float16 and dropped after export (the benchmark then reads the package's
    memory map, as the server does), so 10M Gaussians fit this machine."""
    g = torch.Generator().manual_seed(0)
    means = torch.rand(n, 3, generator=g)
    gs = GaussianSet.from_activated(
        means, torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4), torch.full((n, 3), 0.01), torch.full((n,), 0.9)
    )
    emb, copies = scene_embeddings(n, D, seed=1, means=means, dtype=torch.float16)
    canon_vecs = safe_normalize(torch.randn(4, D, generator=g))
    t0 = time.perf_counter()
    p = export_scene(folder / "text", gs, torch.arange(n), emb, "bench/text", canon_vecs)
    return p, copies, time.perf_counter() - t0


def stored(pkg: Path) -> tuple[torch.Tensor, torch.Tensor]:
    """The package's float16 embeddings [M,D] (memory map) and each row's best canonical dot [M] (the
    stored float32 dots the engine reads)."""
    from fmgs.io.mmap_tensors import mmap_torch

    f = pkg / "embeddings.safetensors"
    return mmap_torch(f, "embeddings"), mmap_torch(f, "canonical").amax(1)


def ks_for(n: int) -> list[int]:
    return [k for k in (1, 100, 10_000) if k <= n // 4]


def measure(n: int, queries: int, tmp: Path, peers: bool = True) -> dict:
    """Every measurement at one scene size: ours first (the package paged in), then faiss built from the
    package's memory map (its indexes and ours never resident together: 10M fits 24 GB)."""
    res: dict = {"gaussians": n, "dim": D, "queries_per_set": queries, "threads": 1, "sets": {}}
    pkg, copies, res["export_s"] = package(tmp, n)
    emb, cmax = stored(pkg)
    rss0 = rss_gb()
    t0 = time.perf_counter()
    eng = SceneEngine.open(pkg, EngineConfig())
    res["fmgs_open_s"] = time.perf_counter() - t0
    res["fmgs_open_rss_gb"] = rss_gb() - rss0
    ix = eng.index
    res["fmgs_bytes"] = (ix.nbytes() - ix.basis_nbytes()) / n + 8
    res["fmgs_path"] = "exact float32" if ix.exact else f"compact rank {ix.state.rank}"
    t2 = ix.second_tier
    if t2 is not None:
        head = f" (head {t2.head})" if t2.tail is not None else ""
        res["fmgs_path"] += f", second tier rank {t2.rank}{head} memory-mapped"
    res["fmgs_state_file_bytes"] = (pkg / "query_state.safetensors").stat().st_size / n
    sets = query_sets(emb, copies, queries)
    units = {name: eng.unit(sets[name]) for name in QUERY_SETS}  # the vectors the engine ranks by
    page_in(pkg)
    eng.text_query(sets["near"][0], 10)  # compile the kernels
    # The batch first, as a served scene is (paged in, nothing else held): after the brute force over
    # 10M float16 rows below, the same eight-text pass took 3x its time in this process.
    batch(eng, sets, res)
    rows: dict = {}  # (set, k) -> per-query lists
    truth: dict = {}  # (set, k, j) -> the exact top k rows, best first
    for name in QUERY_SETS:
        m, best = margins(emb, cmax, units[name])
        for k in ks_for(n):
            row = rows.setdefault((name, k), {"ours_ms": [], "ours_rescored": [], "ours_recall": []})
            row["best_cosine"] = best
            for j, q_in in enumerate(sets[name]):
                t = top_of(m[j], k)
                truth[name, k, j] = t
                t0 = time.perf_counter()
                a = eng.text_query(q_in, k)
                row["ours_ms"].append((time.perf_counter() - t0) * 1e3)
                row["ours_rescored"].append(a.rescored)
                row["ours_recall"].append(recall(a.index.numpy(), t, m[j].numpy()))
                assert np.array_equal(a.index.numpy(), t), f"{name} k={k}: not the exact ranking"
        del m
        print(name, "ours done", flush=True)
    del eng, ix
    gc.collect()
    flat = 4 * (D + 1) * n < 0.4 * _mem_total()
    res["faiss_flat_skipped"] = not flat
    fx = build(emb, cmax, flat=flat) if peers else {}
    for f, d in fx.items():
        res[f"{f}_build_s"], res[f"{f}_bytes"] = d["build_s"], d["bytes"]
    if fx:
        res["faiss_ivf_nlist"] = fx[IVF]["nlist"]
    for name in QUERY_SETS:
        for k in ks_for(n):
            row = rows[name, k]
            for f in fx:
                row[f"{f}_ms"], row[f"{f}_recall"] = [], []
            for j, q in enumerate(units[name]):
                t = truth[name, k, j]
                for f, d in fx.items():
                    ids, ms = timed_search(d, q, k)
                    at = torch.from_numpy(np.append(ids[ids >= 0], t[-1]))
                    m = margins(emb[at], cmax[at], q[None])[0][0]  # the answer's and the k-th, together
                    row[f"{f}_ms"].append(ms)
                    row[f"{f}_recall"].append(float((m[:-1] >= m[-1]).sum()) / k)
            res["sets"][f"{name}/k={k}"] = summarise(row)
            print(name, k, {a: round(b, 3) for a, b in res["sets"][f"{name}/k={k}"].items()}, flush=True)
    return res


def summarise(row: dict) -> dict:
    out = {"best_cosine_median": float(row["best_cosine"].median())}
    for key, v in row.items():
        if key.endswith("_ms"):
            out[key[:-3] + "_ms_median"] = statistics.median(v)
            out[key[:-3] + "_ms_p90"] = float(np.percentile(v, 90))
        elif key.endswith("recall"):
            out[key + "_mean"] = float(np.mean(v))
            out[key + "_min"] = float(np.min(v))
        elif key == "ours_rescored":
            out["ours_rescored_median"] = float(np.median(v))
    return out


def batch(eng: SceneEngine, sets: dict, res: dict) -> None:
    """A batch of 8 texts against one (CLIP-like and typical queries), and the bound pass alone."""
    ix = eng.index
    for name in ("typical", "clip"):
        qs = sets[name][:8]
        if len(qs) < 8:
            qs = qs.repeat(8, 1)[:8]
        # "One" is each text of the batch asked alone (the median over the 8 and the rounds), so the
        # ratio does not hang on how easy the first text happens to be.
        one, first, eight = [], [], []
        faults = {"one": [0, 0, 0], "eight": [0, 0, 0]}  # _faults() over the timed calls
        for _ in range(3):
            for j, qj in enumerate(qs):
                t0, f0 = time.perf_counter(), _faults()
                eng.text_query(qj, 100)
                one.append(time.perf_counter() - t0)
                _add_since(faults["one"], f0)
                if j == 0:
                    first.append(one[-1])
            t0, f0 = time.perf_counter(), _faults()
            eng.text_query_many(qs, 100)
            eight.append(time.perf_counter() - t0)
            _add_since(faults["eight"], f0)
        # The bound pass alone (every row bounded for the texts, as rank_many starts): its own ratio is a
        # floor under the batch's, whatever the rest costs.
        # Each takes the pass rank_many would choose for it: a text alone, or the eight together.
        qu = eng.unit(qs)
        rescore_first = first_rescore_count(ix, 100)
        passes = choose_first_pass(ix, qu, 100, rescore_first)
        alone = [choose_first_pass(ix, qu[j : j + 1], 100, rescore_first) for j in range(8)]
        kone, keight = [], []
        for _ in range(3):
            for j in range(8):
                t0 = time.perf_counter()
                first_pass_upper(ix, qu[j : j + 1], None, alone[j])
                kone.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            first_pass_upper(ix, qu, None, passes)
            keight.append(time.perf_counter() - t0)
        # Per call: the eight-text batch's, and the 24 single texts' together over 3 (one batch's worth).
        res[f"batch8_{name}_faults"] = [x / 3 for x in faults["eight"]]
        res[f"one8_{name}_faults"] = [x / 3 for x in faults["one"]]
        res[f"bound8_{name}_ms"] = 1e3 * statistics.median(keight)
        res[f"bound1_{name}_ms"] = 1e3 * statistics.median(kone)
        res[f"batch8_{name}_ratio"] = statistics.median(eight) / statistics.median(one)
        res[f"batch8_{name}_ratio_first"] = statistics.median(eight) / statistics.median(first)
        res[f"batch8_{name}_ms"] = 1e3 * statistics.median(eight)
        res[f"one_{name}_ms"] = 1e3 * statistics.median(one)


def _faults() -> tuple[int, int, int]:
    """This process's (major, minor) page faults and bytes read from storage so far. Major faults read the
    disk synchronously, minor ones map a cached page or a fresh one; storage reads also count what the
    kernel's readahead fetched for a sequential pass (/proc/self/io read_bytes; 0 where absent): pages of
    the package that had left the page cache."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    read = 0
    try:
        with open("/proc/self/io") as f:
            read = next((int(x.split()[1]) for x in f if x.startswith("read_bytes:")), 0)
    except OSError:
        pass
    return r.ru_majflt, r.ru_minflt, read


def _add_since(total: list[int], before: tuple[int, int, int]) -> None:
    """Adds what _faults() counted since ``before`` to ``total``, in place."""
    for i, (now, then) in enumerate(zip(_faults(), before, strict=True)):
        total[i] += now - then


def _io(f: list[float]) -> str:
    """_faults() differences as the report prints them."""
    return f"{f[0]:,.0f} / {f[1]:,.0f} faults, {f[2] / 1e6:,.0f} MB"


def _mem_total() -> int:
    with open("/proc/meminfo") as f:
        for line in f:
            if line.startswith("MemTotal:"):
                return int(line.split()[1]) * 1024
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--gaussians", default="1000000", help="scene sizes, comma-separated (e.g. 1000000,10000000)"
    )
    ap.add_argument("--queries", type=int, default=12, help="queries per set")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--stem", default="TEXT", help="report file names (STEM.md, STEM.json)")
    ap.add_argument(
        "--no-peers", action="store_true", help="ours only (no faiss: its 10M build takes 28 min)"
    )
    args = ap.parse_args()
    sizes = [int(x) for x in args.gaussians.split(",")]
    if args.quick:
        sizes, args.queries = [50_000], 3
    one_thread()
    import faiss

    faiss.omp_set_num_threads(1)
    results = []
    info = machine()
    stem = "TEXT_QUICK" if args.quick else args.stem
    args.out.mkdir(parents=True, exist_ok=True)
    for n in sizes:
        with tempfile.TemporaryDirectory() as tmp:
            results.append(measure(n, args.queries, Path(tmp), peers=not args.no_peers))
        gc.collect()
        info["date"] = dt.datetime.now().isoformat(timespec="seconds")
        out = {"machine": info, "text": results[0], "sizes": results}
        (args.out / f"{stem}.json").write_text(json.dumps(out, indent=1))  # after every size
    (args.out / f"{stem}.md").write_text(report(results, info, args.quick))
    print((args.out / f"{stem}.md").read_text())
    return 0


def report(results: list[dict], info: dict, quick: bool) -> str:
    sizes = ", ".join(f"{r['gaussians']:,}" for r in results)
    L = [
        "# Text queries: certified exact answers against faiss",
        "",
        f"Machine: {info.get('cpu', '?')}, {info.get('cores', '?')} cores, one thread for every engine; "
        f"{info.get('date', '')}. {'QUICK size: completion only.' if quick else ''}",
        f"Scenes: {sizes} field-like Gaussians (D={results[0]['dim']}, clone ties), "
        f"{results[0]['queries_per_set']} queries per set (benchmarks/query_sets.py), all sizes in one run. "
        "Reproduce: `pip install faiss-cpu; python -m benchmarks.text"
        + (f" --gaussians {','.join(str(r['gaussians']) for r in results)}`." if len(results) > 1 else "`."),
        "",
        "Ours: `SceneEngine.open` + `text_query` on the exported package, every answer checked equal to the "
        "float64 brute force (rows and order). faiss: the same float16 embeddings with the margin trick, "
        "built from the package's memory map after ours was measured (never resident together).",
        "",
    ]
    for res in results:
        L += size_section(res)
    if len(results) > 1:
        L += scaling_section(results)
    return "\n".join(L)


def size_section(res: dict) -> list[str]:
    n = res["gaussians"]
    peers = "faiss_ivf_nlist" in res  # False: measured with --no-peers
    flat = peers and not res.get("faiss_flat_skipped")
    L = [
        f"## {n:,} Gaussians",
        "",
        "| engine | resident bytes/Gaussian | build s | open s |",
        "|---|---|---|---|",
        f"| ours ({res['fmgs_path']}; compact state in the package: "
        f"{res.get('fmgs_state_file_bytes', 0):.0f} bytes/Gaussian on disk) | {res['fmgs_bytes']:.0f} | "
        f"{res['export_s']:.1f} (export) | {res['fmgs_open_s']:.2f} |",
        (
            f"| faiss IndexFlatIP | {res['faiss_flat_bytes']} | {res['faiss_flat_build_s']:.1f} | in memory |"
            if flat
            else f"| faiss IndexFlatIP | {4 * (res['dim'] + 1)} | not run: "
            + (
                f"{4 * (res['dim'] + 1) * n / 1e9:.1f} GB does not fit beside the rest on this machine | |"
                if peers
                else "--no-peers | |"
            )
        ),
        (
            f"| faiss IVF{res['faiss_ivf_nlist']},SQ8 + fp16 refine 1000, nprobe 64 | "
            f"{res['faiss_ivf_sq8_refine_bytes']} | {res['faiss_ivf_sq8_refine_build_s']:.1f} | in memory |"
            if peers
            else "| faiss IVF-SQ8 + refine | | not run: --no-peers | |"
        ),
        "",
        "Rows rescored: rows whose float16 embedding was read (a float32 pass with a proven bound, then "
        "float64 for those it cannot settle).",
        "",
        "| set / K | best cos | ours ms (p90) | rows rescored | ours recall | flat ms | flat recall | "
        "IVF-SQ8 ms | IVF-SQ8 recall (min) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for key, s in res["sets"].items():
        fl = f"{s['faiss_flat_ms_median']:.1f} | {s['faiss_flat_recall_mean']:.3f}" if flat else "- | -"
        L.append(
            f"| {key} | {s['best_cosine_median']:.2f} | {s['ours_ms_median']:.1f} ({s['ours_ms_p90']:.1f}) | "
            f"{s['ours_rescored_median']:,.0f} | {s['ours_recall_mean']:.3f} | {fl} | "
            + (
                f"{s['faiss_ivf_sq8_refine_ms_median']:.1f} | "
                f"{s['faiss_ivf_sq8_refine_recall_mean']:.3f} ({s['faiss_ivf_sq8_refine_recall_min']:.2f}) |"
                if peers
                else "- | - |"
            )
        )
    L += [
        "",
        "A batch of 8 texts (`text_query_many`, top 100) against each of its texts asked alone (median over "
        "the 8 texts and 3 rounds; in brackets, against the batch's first text alone, as earlier reports "
        f"measured): typical queries {res['batch8_typical_ms']:.0f} ms against {res['one_typical_ms']:.1f} "
        f"ms, **{res['batch8_typical_ratio']:.2f}x** ({res['batch8_typical_ratio_first']:.2f}x); CLIP-like "
        f"{res['batch8_clip_ms']:.0f} ms against {res['one_clip_ms']:.1f} ms, "
        f"**{res['batch8_clip_ratio']:.2f}x** ({res['batch8_clip_ratio_first']:.2f}x); batch medians of 3. "
        "Per batch, against its 8 texts asked alone: page faults (major, which read the disk, / minor) and "
        "MB read from storage (readahead included: pages of the package that had left the page cache): "
        + "; ".join(
            f"{label} {_io(res[f'batch8_{name}_faults'])} against {_io(res[f'one8_{name}_faults'])}"
            for name, label in (("typical", "typical"), ("clip", "CLIP-like"))
        )
        + ".",
        "",
        "The pass that bounds every row (the first tier for typical texts; for CLIP-like ones, the first "
        "tier and the second tier's head for one text, the whole second tier for eight) alone, 8 texts "
        "against one: typical "
        f"{res['bound8_typical_ms']:.0f} ms against {res['bound1_typical_ms']:.1f} ms "
        f"({res['bound8_typical_ms'] / res['bound1_typical_ms']:.2f}x), CLIP-like "
        f"{res['bound8_clip_ms']:.0f} ms against {res['bound1_clip_ms']:.1f} ms "
        f"({res['bound8_clip_ms'] / res['bound1_clip_ms']:.2f}x). One text's pass is bound by reading "
        "the codes, eight texts' by the multiply-adds (8 x 64 or 8 x 256 per row).",
        "",
    ]
    return L


def scaling_section(results: list[dict]) -> list[str]:
    """Each larger size's median latency over the smallest's, per query set and K (same run)."""
    base = results[0]
    L = [
        f"## Scaling from {base['gaussians']:,} Gaussians (same run)",
        "",
        "| set / K | "
        + " | ".join(f"ours at {r['gaussians']:,}" for r in results[1:])
        + " | "
        + " | ".join(f"IVF-SQ8 at {r['gaussians']:,}" for r in results[1:])
        + " |",
        "|---|" + "---|" * (2 * (len(results) - 1)),
    ]
    ratios: dict[int, list[float]] = {r["gaussians"]: [] for r in results[1:]}
    for key, b in base["sets"].items():
        cells, peer = [], []
        for r in results[1:]:
            s = r["sets"].get(key)
            if s is None:
                cells.append("-")
                peer.append("-")
                continue
            x = s["ours_ms_median"] / b["ours_ms_median"]
            ratios[r["gaussians"]].append(x)
            cells.append(f"{s['ours_ms_median']:.0f} ms ({x:.1f}x)")
            if "faiss_ivf_sq8_refine_ms_median" not in s:  # --no-peers
                peer.append("-")
                continue
            y = s["faiss_ivf_sq8_refine_ms_median"] / b["faiss_ivf_sq8_refine_ms_median"]
            peer.append(f"{s['faiss_ivf_sq8_refine_ms_median']:.0f} ms ({y:.1f}x)")
        L.append(f"| {key} | " + " | ".join(cells + peer) + " |")
    L.append("")
    for n, xs in ratios.items():
        if xs:
            L.append(
                f"Ours at {n:,} over {base['gaussians']:,}: median {statistics.median(xs):.1f}x, "
                f"{min(xs):.1f}-{max(xs):.1f}x over the query sets and K (target: within "
                f"{n / base['gaussians']:.0f}x)."
            )
    L.append("")
    return L


if __name__ == "__main__":
    sys.exit(main())
