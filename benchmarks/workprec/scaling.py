"""Scaling section: text-query latency and resident state against the number of embedded Gaussians, render
time against Gaussians and pixels, end-to-end gRPC latency against concurrent clients; growth fits."""

from __future__ import annotations

import math
import os
import statistics
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks.common import D, med_ms
from benchmarks.workprec.measure import GPU_NOTE, fit_growth, interleaved, pct, set_threads, with_threads
from benchmarks.workprec.plots import figure, save
from benchmarks.workprec.pose import render_scene
from benchmarks.workprec.sizes import ScalingSizes
from benchmarks.workprec.text import field_scene, no_rerank


def tiled(index, n: int, emb16: torch.Tensor):
    """A compact state of n rows: ``index``'s codes, bound norms and canonical dots tiled, rescoring from
    ``emb16`` rows modulo its size (latency and memory only: the scores repeat)."""
    from fmgs.query.index import EmbeddingIndex
    from fmgs.query.state import QueryState

    t = math.ceil(n / index.num)
    m = len(emb16)

    def read_rows(rows: np.ndarray) -> torch.Tensor:
        return emb16[torch.from_numpy(rows % m)].float()

    st = index.state
    rep = lambda x: x.repeat(t, *([1] * (x.ndim - 1)))[:n].contiguous()  # noqa: E731
    state = QueryState(
        st.basis, st.scales, rep(st.codes), rep(st.err_norm), rep(st.res_norm), st.code_norm_max
    )
    return EmbeddingIndex(None, rep(index.canonical), index.cfg, state, read_rows)


def query_fn(index, threads: int, queries: torch.Tensor) -> Callable[[int], Any]:
    """i -> index.rank(queries[i], 100) on ``threads`` threads."""

    def run(i: int):
        set_threads(threads)
        return index.rank(queries[i], 100)

    return run


def text_scaling(sz: ScalingSizes, threads: int) -> list[dict]:
    """Latency and resident state of text queries against the number of embedded Gaussians."""
    from fmgs.query.index import EmbeddingIndex, IndexConfig

    cores = os.cpu_count() or 1
    rows, last = [], None
    for n in (*sz.text_built, *sz.text_tiled):
        if n in sz.text_built:
            fs = field_scene(n, sz.text_queries)
            emb16 = fs.embeddings.half()
            cd16 = emb16.float() @ fs.canonical.T
            compact = EmbeddingIndex.build(emb16, cd16, IndexConfig(exact_below=0))
            exact = EmbeddingIndex.build(emb16, cd16, IndexConfig(rank=0))  # the engine's exact state
            queries = fs.queries
            last = (compact, emb16, queries)
            del fs
            how = "built (fp16 package values)"
        else:
            compact = tiled(last[0], n, last[1])
            exact, queries = None, last[2]
            how = f"tiled from {last[0].num:,}"
        settings = {
            "compact": (compact, threads),
            "compact_all_cores": (compact, cores),
            "compact_no_rerank": (no_rerank(compact), threads),
        }
        if exact is not None:
            settings["exact"] = (exact, threads)
        fns = {k: query_fn(ix, nt, queries) for k, (ix, nt) in settings.items()}
        times, _ = interleaved(fns, len(queries), warmup=3)
        set_threads(threads)
        row = {
            "gaussians": n,
            "state": how,
            **{f"{k}_ms": med_ms(v) for k, v in times.items()},
            "compact_bytes": compact.nbytes() + 8 * n,
            "exact_bytes": (exact.nbytes() + 8 * n) if exact is not None else n * (4 * D + 28),
            "exact_built": exact is not None,
        }
        print(f"  text scaling {n:,}: " + ", ".join(f"{k} {med_ms(v):.2f} ms" for k, v in times.items()))
        rows.append(row)
        del compact, exact
    return rows


def render_scaling(sz: ScalingSizes, threads: int) -> tuple[list[dict], list[dict]]:
    """Render time (5 channels, cpu backend, default tiles) against Gaussian count and pixel count."""
    cores = os.cpu_count() or 1
    by_count = [
        _render_row(f"synthetic-{n}", *sz.render_size, sz.render_reps, threads, cores)
        for n in sz.render_counts
    ]
    by_pixels = [
        _render_row(sz.render_pixels_scene, w, h, sz.render_reps, threads, cores)
        for w, h in sz.render_pixel_sizes
    ]
    return by_count, by_pixels


def _render_row(scene: str, w: int, h: int, reps: int, threads: int, cores: int) -> dict:
    from fmgs.render import rasterize

    means, quats, scales, opac, cam = render_scene(scene, w, h)
    feats = torch.rand(len(means), 5, generator=torch.Generator().manual_seed(0))
    out = {}

    def render():
        out["r"] = rasterize(means, quats, scales, opac, feats, cam, backend="cpu")

    fns = {"one": lambda i: with_threads(threads, render)(), "all": lambda i: with_threads(cores, render)()}
    times, _ = interleaved(fns, reps, warmup=2)
    set_threads(threads)
    r = out["r"]
    row = {
        "scene": scene,
        "gaussians": len(means),
        "width": w,
        "height": h,
        "pixels": w * h,
        "ms": med_ms(times["one"]),
        "ms_all_cores": med_ms(times["all"]),
        "visible": int(r.visible.sum()),
        "pairs": int(r.n_contrib.long().sum()),
    }
    print(f"  render {scene} {w}x{h}: {row['ms']:.1f} ms ({row['ms_all_cores']:.1f} ms on all cores)")
    return row


def grpc_scaling(sz: ScalingSizes, work: Path) -> list[dict]:
    """End-to-end text-query latency through gRPC on loopback against the number of concurrent clients
    (the server as ``fmgs serve`` runs it: default limits, workers = cores, default threads)."""
    from benchmarks.common import TableEncoder, export, gaussians_from
    from fmgs_client.load import LoadConfig, run_load
    from fmgs_server.config import ServerConfig
    from fmgs_server.server import start_server

    fs = field_scene(sz.grpc_gaussians, 16)
    models = work / "grpc-models"
    export(models / "text", gaussians_from(fs.scene), fs.embeddings, fs.canonical)
    enc = TableEncoder(fs.queries, fs.canonical)
    texts = tuple(f"q{i}" for i in range(len(fs.queries)))
    set_threads(os.cpu_count() or 1)
    srv = start_server(ServerConfig(models=models, port=0), encoder_factory=lambda i: enc)
    rows = []
    try:
        run_load(srv.address, LoadConfig("text", texts, clients=1, requests=2 * len(texts), render_every=0))
        for c in sz.grpc_clients:
            n = max(40, c * sz.grpc_requests_per_client)
            rep = run_load(srv.address, LoadConfig("text", texts, clients=c, requests=n, render_every=0))
            if not rep.ok:  # no latency to report: the run is broken, not a figure
                raise RuntimeError(f"gRPC scaling: no request succeeded with {c} clients ({dict(rep.codes)})")
            rows.append(
                {
                    "clients": c,
                    "requests": rep.sent,
                    "ok": rep.ok,
                    "median_ms": statistics.median(rep.latencies_ms),
                    "p90_ms": rep.percentile(90),
                    "p99_ms": rep.percentile(99),
                    "throughput": rep.throughput,
                    "codes": dict(rep.codes),
                    "workers": srv.config.compute_slots,
                }
            )
            print(f"  gRPC {c} clients: {rep.summary()}", flush=True)
    finally:
        srv.stop(0)
    return rows


def section(sz: ScalingSizes, work: Path, threads: int) -> dict:
    text = text_scaling(sz, threads)
    by_count, by_pixels = render_scaling(sz, threads)
    grpc_rows = grpc_scaling(sz, work)
    set_threads(threads)
    fits = {
        "text_compact": fit_growth([r["gaussians"] for r in text], [r["compact_ms"] for r in text])._asdict(),
        "text_no_rerank": fit_growth(
            [r["gaussians"] for r in text], [r["compact_no_rerank_ms"] for r in text]
        )._asdict(),
        "render_gaussians": fit_growth(
            [r["gaussians"] for r in by_count], [r["ms"] for r in by_count]
        )._asdict(),
        "render_pixels": fit_growth([r["pixels"] for r in by_pixels], [r["ms"] for r in by_pixels])._asdict(),
        "grpc_clients": fit_growth(
            [r["clients"] for r in grpc_rows], [r["median_ms"] for r in grpc_rows]
        )._asdict(),
    }
    ex = [r for r in text if r["exact_built"]]
    if len(ex) >= 2:
        fits["text_exact"] = fit_growth([r["gaussians"] for r in ex], [r["exact_ms"] for r in ex])._asdict()
    return {
        "config": asdict(sz),
        "text": text,
        "render_gaussians": by_count,
        "render_pixels": by_pixels,
        "grpc": grpc_rows,
        "fits": fits,
    }


def _fit_line(name: str, f: dict, unit: str) -> str:
    ms = unit == "client"  # per-unit times of milliseconds read better in ms
    t = (lambda ns: f"{ns / 1e6:.3g} ms") if ms else (lambda ns: f"{ns:.3g} ns")
    return (
        f"| {name} | {f['model']} | {f['exponent']:.2f} | {f['fixed_ms']:.2f} | {t(f['per_unit_ns'])}/{unit} "
        f"| {pct(f['rel_rms_linear'])} | {pct(f['rel_rms_nlogn'])} | {f['linear_lo']:,.0f} to "
        f"{f['linear_hi']:,.0f} | {t(f['best_unit_ns'])} / {t(f['top_unit_ns'])} |"
    )


def markdown(sec: dict, img: str) -> list[str]:
    """The section's text and tables in REPORT.md."""
    t, gr = sec["text"], sec["grpc"]
    L = [
        "## 5. Scaling",
        "",
        "Text queries (top-100) on field-like scenes built like packages; sizes marked *tiled* reuse the "
        "largest built scene's int8 coefficients and canonical dots tiled to the size (the compact state "
        "built directly, not through an exported package; re-ranking reads the float16 rows modulo the "
        "built size): their latency and memory are real, their answers are not meaningful. The exact "
        "float32 state is built up to the largest built size; beyond it its memory is computed (4*D + 28 "
        "bytes per Gaussian), not measured. Memory: bytes of the resident query state (int8 coefficients, "
        "basis, canonical dots, scene index). Renders: 5 channels, cpu backend, tile 16.",
        "",
        f"![scaling]({img})",
        "",
        "| Gaussians | state | compact ms | compact ms, all cores | no re-rank ms | exact ms | compact MiB "
        "(B/Gaussian) | exact MiB | GPU |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in t:
        ex = f"{r['exact_ms']:.2f}" if "exact_ms" in r else "not built"
        exb = f"{r['exact_bytes'] / 2**20:,.0f}" + ("" if r["exact_built"] else " (computed)")
        L.append(
            f"| {r['gaussians']:,} | {r['state']} | {r['compact_ms']:.2f} | {r['compact_all_cores_ms']:.2f} "
            f"| {r['compact_no_rerank_ms']:.2f} | {ex} | {r['compact_bytes'] / 2**20:,.1f} "
            f"({r['compact_bytes'] / r['gaussians']:.0f}) | {exb} | {GPU_NOTE} |"
        )
    L += [
        "",
        "| scene | Gaussians | size | ms (1 thread) | ms (all cores) | contributing pairs / pixel | GPU |",
        "|---|---:|---|---:|---:|---:|---|",
    ]
    for r in (*sec["render_gaussians"], *sec["render_pixels"]):
        L.append(
            f"| {r['scene']} | {r['gaussians']:,} | {r['width']}x{r['height']} | {r['ms']:.1f} | "
            f"{r['ms_all_cores']:.1f} | {r['pairs'] / r['pixels']:.1f} | {GPU_NOTE} |"
        )
    L += [
        "",
        "gRPC: text queries (top-100) from N concurrent clients (fmgs_client.load.run_load, one channel "
        f"each) to an in-process server on loopback serving a {sec['config']['grpc_gaussians']:,}-Gaussian "
        f"scene package as `fmgs serve` would (compute slots = {gr[0]['workers'] if gr else '?'}, text "
        "embeddings cached).",
        "",
        "| clients | requests | OK | median ms | p90 ms | p99 ms | answered / s |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in gr:
        L.append(
            f"| {r['clients']} | {r['requests']} | {r['ok']} | {r['median_ms']:.1f} | {r['p90_ms']:.1f} | "
            f"{r['p99_ms']:.1f} | {r['throughput']:.1f} |"
        )
    f = sec["fits"]
    L += [
        "",
        "Growth fits: exponent = slope of log time against log size over the largest half of the sizes; "
        "linear fit time = fixed + per-unit x size (least relative squares) and the same with size x "
        "log2(size); 'linear regime' = the contiguous sizes around the cheapest time per unit whose time "
        "per unit stays within 25% of it (below it a fixed cost dominates, above it each unit costs more); "
        "last column: the cheapest time per unit and the time per unit at the largest size.",
        "",
        "| series | growth | exponent | fixed ms | per unit | rel. RMS linear | rel. RMS n log n | linear "
        "regime | per unit: best / largest |",
        "|---|---|---:|---:|---:|---:|---:|---|---:|",
    ]
    names = {
        "text_compact": ("text query, compact default", "Gaussian"),
        "text_no_rerank": ("text query, compact, no re-rank", "Gaussian"),
        "text_exact": ("text query, exact float32", "Gaussian"),
        "render_gaussians": ("render vs Gaussians", "Gaussian"),
        "render_pixels": ("render vs pixels", "pixel"),
        "grpc_clients": ("gRPC median latency vs clients", "client"),
    }
    L += [_fit_line(names[k][0], v, names[k][1]) for k, v in f.items()]
    return L


def growth_words(g: dict, unit: str) -> str:
    """'linear from A to B (... ns per unit), a fixed cost below A, +x% per unit above B' in words."""
    out = f"{g['model']} (exponent {g['exponent']:.2f} over the larger sizes); " + (
        f"linear from {g['linear_lo']:,.0f} to {g['linear_hi']:,.0f} {unit} at {g['best_unit_ns']:.3g} ns "
        "each"
        if g["linear_hi"] > g["linear_lo"]
        else f"cheapest per unit at {g['linear_lo']:,.0f} {unit} ({g['best_unit_ns']:.3g} ns each)"
    )
    if g["fixed_ms"] > 0:
        out += f", a fixed {g['fixed_ms']:.1f} ms dominating below"
    if g["top_unit_ns"] > 1.25 * g["best_unit_ns"]:
        out += f", {100 * (g['top_unit_ns'] / g['best_unit_ns'] - 1):.0f}% more per unit at the largest size"
    return out


def reading(sec: dict) -> list[str]:
    """The scaling part of the reading: how each time grows."""
    f = sec["fits"]
    tc, tn, rp, rg, gc = (
        f["text_compact"],
        f["text_no_rerank"],
        f["render_pixels"],
        f["render_gaussians"],
        f["grpc_clients"],
    )
    L = [
        "- **Scaling.** Text query, compact default: "
        + growth_words(tc, "Gaussians")
        + "; without re-rank: "
        + growth_words(tn, "Gaussians")
        + f". Render: {growth_words(rp, 'pixels')}; against Gaussian count (at about the same blended "
        f"pairs per pixel) exponent {rg['exponent']:.2f}. gRPC: median latency {gc['model']} in clients "
        f"({gc['per_unit_ns'] / 1e6:.1f} ms per extra client), throughput flat once the compute slots "
        "are busy: the server is compute bound and queues fairly."
    ]
    t = sec["text"]
    ratio = statistics.median(r["compact_all_cores_ms"] / r["compact_ms"] for r in t)
    rows = sec["render_gaussians"] + sec["render_pixels"]
    rratio = statistics.median(r["ms_all_cores"] / r["ms"] for r in rows)
    L.append(
        f"  On all cores the compact text query took {ratio:.2f}x and the render {rratio:.2f}x their "
        "one-thread time (medians over the sizes): on this shared machine the second core is mostly "
        "someone else's, so the single-thread figures are the ones to read."
    )
    return L


def plot(sec: dict, path: Path, stamp: str) -> None:
    plt, fig, axes = figure(3, 2, width=5.2)
    t = sec["text"]
    n = [r["gaussians"] for r in t]
    ax = axes[0]
    for key, label in (
        ("compact_ms", "compact default (rank 64 + re-rank)"),
        ("compact_all_cores_ms", "compact default, all cores"),
        ("compact_no_rerank_ms", "compact, no re-rank"),
        ("exact_ms", "exact float32"),
    ):
        xs = [r["gaussians"] for r in t if key in r]
        ax.plot(xs, [r[key] for r in t if key in r], "o-", label=label)
    ax.set(xscale="log", yscale="log", xlabel="embedded Gaussians", ylabel="median ms per text query")
    ax.set_title("text query latency", fontsize=9)
    ax = axes[1]
    ax.plot(n, [r["compact_bytes"] / 2**20 for r in t], "o-", label="compact state")
    built = [r for r in t if r["exact_built"]]
    ax.plot(
        [r["gaussians"] for r in built],
        [r["exact_bytes"] / 2**20 for r in built],
        "o-",
        label="exact float32",
    )
    ax.plot(
        [r["gaussians"] for r in t if r is built[-1] or not r["exact_built"]],
        [r["exact_bytes"] / 2**20 for r in t if r is built[-1] or not r["exact_built"]],
        "o--",
        color="C1",
        label="exact float32, computed (not built)",
    )
    ax.set(xscale="log", yscale="log", xlabel="embedded Gaussians", ylabel="resident query state (MiB)")
    ax.set_title("text query memory", fontsize=9)
    ax = axes[2]
    g = sec["render_gaussians"]
    ax.plot([r["gaussians"] for r in g], [r["ms"] for r in g], "o-", label="1 thread")
    ax.plot([r["gaussians"] for r in g], [r["ms_all_cores"] for r in g], "o--", label="all cores")
    ax.set(xscale="log", yscale="log", xlabel="Gaussians", ylabel="render ms (5 channels, cpu)")
    ax.set_title(f"render vs Gaussians ({g[0]['width']}x{g[0]['height']})", fontsize=9)
    ax = axes[3]
    px = sec["render_pixels"]
    ax.plot([r["pixels"] for r in px], [r["ms"] for r in px], "o-", label="1 thread")
    ax.plot([r["pixels"] for r in px], [r["ms_all_cores"] for r in px], "o--", label="all cores")
    ax.set(xscale="log", yscale="log", xlabel="pixels", ylabel="render ms (5 channels, cpu)")
    ax.set_title(f"render vs pixels ({px[0]['scene']})", fontsize=9)
    ax = axes[4]
    gr = sec["grpc"]
    c = [r["clients"] for r in gr]
    ax.plot(c, [r["median_ms"] for r in gr], "o-", label="median")
    ax.plot(c, [r["p90_ms"] for r in gr], "o--", label="p90")
    ax.set(xscale="log", yscale="log", xlabel="concurrent clients", ylabel="end-to-end ms per text query")
    ax.set_title("gRPC latency vs concurrency", fontsize=9)
    ax = axes[5]
    ax.plot(c, [r["throughput"] for r in gr], "o-", label="answered per second")
    ax.set(xscale="log", xlabel="concurrent clients", ylabel="text queries per second")
    ax.set_ylim(bottom=0)
    ax.set_title("gRPC throughput", fontsize=9)
    for a in axes:
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=7)
    save(plt, fig, path, "Scaling", stamp)
