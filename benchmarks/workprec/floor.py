"""Physical-limit section: this machine's memory bandwidth and arithmetic rate, and each hot path's
measured time (int8 scan, top-k, text queries, renders) as a multiple of the floor they imply."""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks.common import D, med_ms
from benchmarks.workprec.measure import (
    GPU_NOTE,
    PROJECT_FLOPS,
    RENDER_FLOPS_PER_PAIR,
    Cost,
    exact_query_cost,
    floor_ms,
    measure_rates,
    render_cost,
    set_threads,
    text_query_cost,
    timed,
)
from benchmarks.workprec.plots import figure, save
from benchmarks.workprec.pose import render_scene
from benchmarks.workprec.sizes import FloorSizes
from benchmarks.workprec.text import no_rerank


def random_compact_state(n: int, rank: int = 64, seed: int = 0):
    """A compact state built directly: random int8 coefficients and canonical dots, a random orthonormal
    basis, re-ranking from a random float16 table of 100K rows (rows modulo its size)."""
    from fmgs.query.index import EmbeddingIndex, IndexConfig

    g = torch.Generator().manual_seed(seed)
    coeffs = torch.randint(-127, 128, (n, rank), generator=g, dtype=torch.int8)
    basis = torch.linalg.qr(torch.randn(D, rank, generator=g))[0].T.contiguous()
    scales = torch.full((rank,), 1.0 / 127 / math.sqrt(rank))
    canon = torch.randn(n, 4, generator=g) * 0.1
    table = torch.nn.functional.normalize(torch.randn(100_000, D, generator=g), dim=1).half()

    def read_rows(rows: np.ndarray) -> torch.Tensor:
        return table[torch.from_numpy(rows % len(table))].float()

    from fmgs.query.state import QueryState

    zeros = torch.zeros(n, dtype=torch.float16)  # latency only: bounds that rescore as few rows as possible
    state = QueryState(basis.double(), scales, coeffs, zeros, zeros, 1.0)
    return EmbeddingIndex(None, canon, IndexConfig(rank=rank, exact_below=0), state, read_rows)


def scan_cases(sz: FloorSizes, q: torch.Tensor):
    """(name, fn, cost, note) of the text-query scans, built one at a time (their states are large)."""
    from fmgs.query.index import EmbeddingIndex, IndexConfig
    from fmgs.query.kernels import int8_dots
    from fmgs.vecmath import safe_normalize

    M = sz.compact_gaussians
    ix = random_compact_state(M)
    W = ix.compact.first_tier_weights(q[None])[0].numpy()
    out = np.empty((M, 1), np.float32)
    shift, A = ix.canonical_max.numpy(), ix.state.codes.numpy()
    yield (
        f"int8 scan kernel, {M:,} x rank 64",
        lambda: int8_dots(A, W, shift, out),
        Cost(M * (64 + 8), 2.0 * M * 64),
        "reads M*r int8 + shift, writes one float32 per Gaussian",
    )
    nr = no_rerank(ix)
    yield (
        f"text query, compact, no re-rank, {M:,}",
        lambda: nr.rank(q, 100),
        text_query_cost(M, 64),
        "scan + top-k",
    )

    def scan_and_rescore():  # the certified query's parts at 1000 rows rescored (random codes bound nothing)
        m = ix.dots(q[None], ix.canonical_max)[:, 0]
        cand = torch.topk(m, 1000, sorted=False).indices
        return ix.exact_dots(cand, q[None])

    yield (
        f"text query, compact scan + 1000 rows rescored exactly, {M:,}",
        scan_and_rescore,
        text_query_cost(M, 64, rerank_rows=1000),
        "scan + top-k + 1000 float16 rows rescored",
    )
    ix = nr = A = out = None
    x = torch.randn(M, generator=torch.Generator().manual_seed(3))
    xn = x.numpy()
    yield (
        f"top-1000 of {M:,} scores, torch.topk (the index's selection)",
        lambda: torch.topk(x, 1000, sorted=False),
        Cost(4 * M, M),
        "reads M float32, about one comparison each",
    )
    yield (
        f"top-1000 of {M:,} scores, numpy argpartition (for comparison)",
        lambda: np.argpartition(xn, M - 1000)[M - 1000 :],
        Cost(4 * M, M),
        "reads M float32, about one comparison each",
    )
    x = xn = None
    Me = sz.exact_gaussians
    emb = safe_normalize(torch.randn(Me, D, generator=torch.Generator().manual_seed(2)))
    ex = EmbeddingIndex.build(emb, emb[:, :4].contiguous(), IndexConfig(rank=0))
    yield (
        f"text query, exact float32, {Me:,}",
        lambda: ex.rank(q, 100),
        exact_query_cost(Me),
        "matrix-vector + top-k",
    )


def section(sz: FloorSizes, threads: int) -> dict:
    from fmgs.render import rasterize
    from fmgs.vecmath import safe_normalize

    set_threads(threads)
    rates = measure_rates(sz.stream_bytes, sz.matmul_n, sz.reps)
    set_threads(os.cpu_count() or 1)
    rates_all = measure_rates(sz.stream_bytes, sz.matmul_n, sz.reps)
    set_threads(threads)
    g = torch.Generator().manual_seed(1)
    q = safe_normalize(torch.randn(D, generator=g))
    rows = []

    def add(name: str, fn: Callable[[], Any], cost: Cost, note: str) -> None:
        fn()
        ts = [timed(fn) for _ in range(sz.reps)]
        ms = med_ms(ts)
        fl = floor_ms(cost, rates)
        bound = "memory" if cost.bytes / rates.bandwidth_gbs > cost.flops / rates.gflops else "arithmetic"
        rows.append(
            {
                "path": name,
                "measured_ms": ms,
                "bytes": cost.bytes,
                "flops": cost.flops,
                "floor_ms": fl,
                "bound": bound,
                "multiple": ms / fl,
                "note": note,
            }
        )
        print(f"  floor {name}: {ms:.2f} ms, floor {fl:.3f} ms ({bound}), x{ms / fl:.1f}", flush=True)

    for name, fn, cost, note in scan_cases(sz, q):
        add(name, fn, cost, note)
    means, quats, scales, opac, cam = render_scene(sz.render_scene, *sz.render_size)
    for ch in (5, D):
        feats = torch.rand(len(means), ch, generator=g)
        r = rasterize(means, quats, scales, opac, feats, cam, backend="cpu")
        pairs = int(r.n_contrib.long().sum())
        add(
            f"render {sz.render_scene} {cam.width}x{cam.height}, {ch} channels, cpu",
            lambda f=feats: rasterize(means, quats, scales, opac, f, cam, backend="cpu"),
            render_cost(pairs, len(means), cam.width * cam.height, ch),
            f"{pairs:,} contributing (pixel, Gaussian) pairs, {pairs / (cam.width * cam.height):.1f} per "
            "pixel",
        )
    return {"config": asdict(sz), "rates": asdict(rates), "rates_all_cores": asdict(rates_all), "rows": rows}


def markdown(sec: dict, img: str) -> list[str]:
    """The section's text and table in REPORT.md."""
    r, ra = sec["rates"], sec["rates_all_cores"]
    L = [
        "## 6. Physical limit",
        "",
        f"This machine, measured here (best of {sec['config']['reps']}): memory read bandwidth "
        f"**{r['bandwidth_gbs']:.1f} GB/s** (sum of a {sec['config']['stream_bytes'] / 2**20:.0f} MiB "
        f"float32 array) and float32 arithmetic **{r['gflops']:.0f} GFLOP/s** "
        f"({sec['config']['matmul_n']}^2 matmul) with the query thread count; on all cores "
        f"{ra['bandwidth_gbs']:.1f} GB/s and {ra['gflops']:.0f} GFLOP/s (other people's jobs share the "
        "cores). Floor = max(bytes / bandwidth, flops / rate) with the query-thread rates; measured = "
        "median of the runs.",
        "",
        "Cost models: text query (compact) reads M*r int8 coefficients + 3 float32 per Gaussian (canonical "
        "shift read, score written, score read by top-k) and does 2*M*r flops; the re-rank adds 1000 rows "
        "x D float16 and 2*5*D flops per row. Exact scan: 4*D + 12 bytes and 2*D flops per Gaussian. "
        f"Render: {RENDER_FLOPS_PER_PAIR} + 2*channels flops per contributing (pixel, Gaussian) pair "
        f"(RenderOutput.n_contrib summed) + {PROJECT_FLOPS} flops per Gaussian for the projection; bytes: "
        "each Gaussian's projected parameters and channels read once, the image written once. Pairs that "
        "are evaluated but fall below alpha_min are not counted, so the render floor is optimistic.",
        "",
        f"![floor]({img})",
        "",
        "| path | measured ms | MB moved | MFLOP | floor ms | bound by | measured / floor | note | GPU |",
        "|---|---:|---:|---:|---:|---|---:|---|---|",
    ]
    for x in sec["rows"]:
        L.append(
            f"| {x['path']} | {x['measured_ms']:.2f} | {x['bytes'] / 1e6:.1f} | {x['flops'] / 1e6:.1f} | "
            f"{x['floor_ms']:.3f} | {x['bound']} | **x{x['multiple']:.1f}** | {x['note']} | {GPU_NOTE} |"
        )
    return L


def reading(sec: dict) -> list[str]:
    """The physical-limit part of the reading: how far each path is from its floor."""
    rows = sec["rows"]
    by = {r["path"].split(",")[0]: r for r in rows}
    L = [
        "- **Physical limit.** "
        + "; ".join(f"{r['path']}: x{r['multiple']:.1f} its {r['bound']} floor" for r in rows)
        + ". The render is far from its arithmetic floor (serial per-pixel blending with an exp per pair, "
        "not the dense multiply-adds the rate was measured on)."
    ]
    k = by.get("int8 scan kernel")
    q = next((r for r in rows if "no re-rank" in r["path"]), None)
    tk = next((r for r in rows if "torch.topk" in r["path"]), None)
    ap = next((r for r in rows if "argpartition" in r["path"]), None)
    if k and q and tk and ap:
        rest = q["measured_ms"] - k["measured_ms"]
        text = (
            f"  The int8 scan itself runs at x{k['multiple']:.1f} its memory floor ({k['measured_ms']:.0f} "
            f"ms), the query without re-rank takes {q['measured_ms']:.0f} ms; selecting the best 1000 scores "
            f"with torch.topk takes {tk['measured_ms']:.0f} ms on its own (x{tk['multiple']:.0f} its floor), "
            f"numpy's argpartition {ap['measured_ms']:.0f} ms."
        )
        if rest > 0 and tk["measured_ms"] >= 0.5 * rest:
            text += " So the selection, not the scan, is most of what the query spends beyond the scan" + (
                "; a partition-based selection (or a threshold inside the scan kernel) would remove most of "
                "it."
                if ap["measured_ms"] < 0.5 * tk["measured_ms"]
                else "."
            )
        L.append(text)
    return L


def plot(sec: dict, path: Path, stamp: str) -> None:
    plt, fig, axes = figure(1, width=10)
    ax = axes[0]
    rows = sec["rows"]
    y = np.arange(len(rows))
    ax.barh(y - 0.2, [r["measured_ms"] for r in rows], 0.4, label="measured (median)")
    ax.barh(y + 0.2, [r["floor_ms"] for r in rows], 0.4, label="floor (max of bytes/bandwidth, flops/rate)")
    for yi, r in zip(y, rows, strict=True):
        ax.annotate(
            f"x{r['multiple']:.1f}",
            (r["measured_ms"], yi - 0.2),
            fontsize=7,
            xytext=(3, -3),
            textcoords="offset points",
        )
    ax.set_yticks(y, [r["path"] for r in rows], fontsize=7)
    ax.set(xscale="log", xlabel="ms")
    ax.invert_yaxis()
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    save(plt, fig, path, "Measured time against the physical floor", stamp)
