"""Text query section: top-100 of a field-like scene's Gaussians for a query vector, every speed knob
(storage dtype, compact rank with and without re-rank, opacity subsets) against the exact float32
reference, and the default measured through the product path (SceneEngine on an exported package)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from benchmarks.server import D, med_ms
from benchmarks.workprec.engine import canonical_vectors, product_engine
from benchmarks.workprec.measure import (
    GPU_NOTE,
    Point,
    e,
    interleaved,
    overlap_error,
    pct,
    sorted_relevancy_error,
)
from benchmarks.workprec.plots import plot_work_precision
from benchmarks.workprec.sizes import TextSizes


class FieldScene(NamedTuple):
    """A scene with field-like per-Gaussian embeddings (benchmarks/server.py ``fieldlike``)."""

    scene: Any
    """benchmarks.scenes.Scene."""
    embeddings: torch.Tensor
    """[N,D] float32, unit norm."""
    canonical: torch.Tensor
    """[4,D] unit canonical vectors."""
    queries: torch.Tensor
    """[Q,D] unit queries near scene embeddings."""


def field_scene(n: int, queries: int, seed: int = 3) -> FieldScene:
    """n synthetic Gaussians (benchmarks/scenes.py) with field-like embeddings and queries near them."""
    from benchmarks.scenes import synthetic
    from benchmarks.server import fieldlike, make_queries

    s = synthetic(n, seed=seed)
    emb = fieldlike(s.means)
    return FieldScene(s, emb, canonical_vectors(), make_queries(emb, queries))


def rank_scores(sim: torch.Tensor, canonical_max: torch.Tensor, k: int):
    """Ranked (fmgs.query.index) from exact scores sim [M]: margin order, ties by row (as the index)."""
    from fmgs.query.index import Ranked
    from fmgs.query.relevancy import TEMPERATURE

    margin = sim - canonical_max
    cand = torch.topk(margin, min(k, len(sim)), sorted=False).indices.sort().values
    rows = cand[torch.sort(margin[cand], descending=True, stable=True).indices]
    return Ranked(rows, torch.sigmoid(TEMPERATURE * margin[rows]), sim[rows])


class Fp16Scan:
    """Exact scores from embeddings stored as float16 (2*D bytes per Gaussian), widened to float32 one
    chunk at a time and dotted in float32."""

    def __init__(self, emb16: torch.Tensor, canonical_dots: torch.Tensor, chunk: int = 32768) -> None:
        self.emb16, self.cmax, self.chunk = emb16, canonical_dots.amax(1), chunk

    def rank(self, q: torch.Tensor, k: int):
        sim = torch.empty(len(self.emb16))
        for s in range(0, len(sim), self.chunk):
            sim[s : s + self.chunk] = self.emb16[s : s + self.chunk].float() @ q
        return rank_scores(sim, self.cmax, k)

    def nbytes(self) -> int:
        return self.emb16.numel() * 2 + self.cmax.numel() * 4


class SubsetScan:
    """Exact float32 scores of a subset of the Gaussians (rows into the full set)."""

    def __init__(self, emb: torch.Tensor, canonical_dots: torch.Tensor, rows: torch.Tensor) -> None:
        self.rows = rows.sort().values
        self.emb = emb[self.rows].contiguous()
        self.cmax = canonical_dots.amax(1)[self.rows].contiguous()

    def rank(self, q: torch.Tensor, k: int):
        r = rank_scores(self.emb @ q, self.cmax, k)
        return r._replace(rows=self.rows[r.rows])

    def nbytes(self) -> int:
        return self.emb.numel() * 4 + self.cmax.numel() * 4 + self.rows.numel() * 8


def most_opaque(opacities: torch.Tensor, fraction: float) -> torch.Tensor:
    """Rows of the ceil(fraction * N) most opaque Gaussians."""
    n = max(1, math.ceil(fraction * len(opacities)))
    return torch.topk(opacities, n).indices


class CompactOnly:
    """The compact state's scores alone, ranked without exact rescoring (not certified): what the
    approximation gives by itself."""

    def __init__(self, index) -> None:
        self.index = index

    def rank(self, q: torch.Tensor, k: int):
        from fmgs.query.certify import order_rows
        from fmgs.query.index import Ranked, served_relevancy

        ix = self.index
        m = ix.dots(q[None], ix.canonical_max)[:, 0]
        top = torch.topk(m, min(k, len(m)), sorted=False).indices
        rows = top[order_rows(m[top], top)]
        return Ranked(rows, served_relevancy(m[rows]), m[rows] + ix.canonical_max[rows])

    def nbytes(self) -> int:
        return self.index.nbytes()


def no_rerank(index) -> CompactOnly:
    """The same compact state, returning compact scores (no exact rescoring)."""
    return CompactOnly(index)


class EngineRanker:
    """SceneEngine.text_query with the ranker interface of the other settings (scene indices are rows:
    the package embeds every Gaussian)."""

    def __init__(self, engine) -> None:
        self.engine = engine

    def rank(self, q: torch.Tensor, k: int):
        from fmgs.query.index import Ranked

        a = self.engine.text_query(q, k)
        return Ranked(a.index, a.relevancy, a.similarity)

    def nbytes(self) -> int:
        return self.engine.index.nbytes()


def engine_path(index) -> str:
    """The setting whose path the engine's index takes ('f16as32' or 'r<rank>')."""
    return "f16as32" if index.exact else f"r{index.cfg.rank}"


def section(sz: TextSizes, work: Path) -> dict:
    from benchmarks.server import gaussians_from
    from fmgs.query.index import EmbeddingIndex, IndexConfig, rank_reference

    fs = field_scene(sz.gaussians, sz.queries)
    emb, n, k = fs.embeddings, sz.gaussians, sz.top_k
    emb16 = emb.half()
    cd32 = emb @ fs.canonical.T
    cd16 = emb16.float() @ fs.canonical.T  # as a package stores them (fmgs.scene.package.export_scene)
    refs = [rank_reference(emb, cd32, q, k) for q in fs.queries]
    spread = float(np.mean([float(r.relevancy[0] - r.relevancy[-1]) for r in refs]))

    engine = product_engine(work / "text-package", gaussians_from(fs.scene), emb, fs.canonical)
    path = engine_path(engine.index)
    settings: dict[str, tuple[str, str, Any, bool]] = {}  # name -> (curve, label, ranker, exact)
    exact = EmbeddingIndex.build(emb, cd32, IndexConfig(rank=0))
    settings["f32"] = ("storage dtype", "float32 (exact)", exact, True)
    f16as32 = EmbeddingIndex.build(emb16, cd16, IndexConfig(rank=0))  # the engine's exact path
    settings["f16as32"] = ("storage dtype", "float16 values held as float32", f16as32, False)
    settings["f16"] = ("storage dtype", "float16, widened per chunk", Fp16Scan(emb16, cd16), False)
    for r in sz.ranks:
        ci = EmbeddingIndex.build(emb16, cd16, IndexConfig(rank=r, exact_below=0, rerank=10))
        settings[f"r{r}"] = ("rank, int8 + exact re-rank of 10k", f"rank {r}", ci, False)
        settings[f"r{r}nr"] = ("rank, int8, no re-rank", f"rank {r}", no_rerank(ci), False)
    for p in sz.subsets:
        sub = SubsetScan(emb, cd32, most_opaque(fs.scene.opacities, p))
        settings[f"sub{p}"] = ("most opaque subset (float32)", f"{p:.0%}", sub, False)
    how = "exact, float16 package" if engine.index.exact else f"rank {engine.index.cfg.rank} + re-rank"
    settings["engine"] = ("product path", f"SceneEngine.text_query ({how})", EngineRanker(engine), False)

    fns = {name: (lambda i, rk=s[2]: rk.rank(fs.queries[i], k)) for name, s in settings.items()}
    times, outs = interleaved(fns, len(fs.queries))
    points = []
    for name, (curve, label, ranker, is_exact) in settings.items():
        ov = [
            overlap_error(o.rows.tolist(), r.rows.tolist(), k) for o, r in zip(outs[name], refs, strict=True)
        ]
        rel = [
            sorted_relevancy_error(o.relevancy, r.relevancy) for o, r in zip(outs[name], refs, strict=True)
        ]
        vs16 = [
            overlap_error(o.rows.tolist(), r.rows.tolist(), k)
            for o, r in zip(outs[name], outs["f16as32"], strict=True)
        ]
        extra = 0 if isinstance(ranker, SubsetScan | Fp16Scan) else n * 8  # + scene index per row
        points.append(
            Point(
                curve,
                label,
                med_ms(times[name]),
                {"overlap": float(np.mean(ov)), "overlap_worst": max(ov), "relevancy": max(rel)},
                exact=is_exact,
                default=name == "engine",
                info={
                    "p90_ms": float(np.percentile(times[name], 90) * 1e3),
                    "bytes_per_gaussian": (ranker.nbytes() + extra) / n,
                    "setting": name,
                    "overlap_vs_f16": float(np.mean(vs16)),
                    "overlap_vs_f16_worst": max(vs16),
                },
            )
        )
    return {
        "config": asdict(sz),
        "gaussians": n,
        "dim": D,
        "points": [asdict(p) for p in points],
        "default_setting": "engine",
        "engine_path": path,
        "reference_spread": spread,
    }


def markdown(sec: dict, img: str) -> list[str]:
    """The section's text and table in REPORT.md."""
    n, cfg = sec["gaussians"], sec["config"]
    L = [
        "## 1. Text query",
        "",
        f"Scene: {n:,} embedded Gaussians with field-like unit embeddings (D = {sec['dim']}; a random "
        "two-layer MLP over Fourier features of the positions, as benchmarks/server.py), 4 canonical "
        f"vectors, {cfg['queries']} queries near scene embeddings, top-{cfg['top_k']}. Reference: "
        "`rank_reference` on the float32 embeddings. Errors: 1 - top-100 overlap (mean over queries / "
        "worst query) and the largest |relevancy difference| position by position along the two sorted "
        "top-100 lists. Time: median per query, every setting run once per query in rotating order. "
        "Compact settings are built like the engine builds them from a package (float16 embeddings, "
        "canonical dots from them, re-rank reading the float16 rows); the opacity subsets rank exact "
        "float32 scores of the most opaque Gaussians only."
        + (
            " The default point is the product path: `SceneEngine.text_query` on a package exported from "
            "these embeddings (`fmgs.scene.package.export_scene`) and opened with the query server's "
            "`EngineConfig`; every other row is an alternative measured on a bare index or scan."
            if any(p["info"].get("setting") == "engine" for p in sec["points"])
            else ""
        ),
        "",
        f"![text query work-precision]({img})",
        "",
        "| knob | setting | median ms | p90 ms | bytes / Gaussian | 1 - overlap (mean / worst) | max "
        "relevancy error | 1 - overlap with exact float16 (mean / worst) | GPU |",
        "|---|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for p in sec["points"]:
        flags = (" **(exact reference)**" if p["exact"] else "") + (" **(default)**" if p["default"] else "")
        L.append(
            f"| {p['curve']} | {p['label']}{flags} | {p['time_ms']:.2f} | {p['info']['p90_ms']:.2f} | "
            f"{p['info']['bytes_per_gaussian']:.0f} | {e(p['errors']['overlap'])} / "
            f"{e(p['errors']['overlap_worst'])} | {e(p['errors']['relevancy'])} | "
            f"{e(p['info'].get('overlap_vs_f16', float('nan')))} / "
            f"{e(p['info'].get('overlap_vs_f16_worst', float('nan')))} | {GPU_NOTE} |"
        )
    L += [
        "",
        "The last column compares with the exact scores of the float16-rounded embeddings (what a package "
        "stores): it separates what the compact scan loses from what float16 storage itself changes.",
    ]
    return L


def rank_choice(s: dict[str, dict], ranks: Sequence[int]) -> str:
    """Why rank 64, from which ranks' re-ranked top-100 equalled the float16 exact one in every query."""
    ok = [r for r in ranks if s[f"r{r}"]["info"].get("overlap_vs_f16_worst", 1) == 0]
    cost = "at 64 B + 28 B per Gaussian (canonical dots, shift, index), under 1 GiB for 10M Gaussians"
    if not ok:
        return f"No rank recovered it in every query here: the default 64 is {cost}."
    below = [r for r in ranks if r < min(ok)]
    if min(ok) == 64:
        miss = "; ".join(
            f"rank {r} missed up to {pct(s[f'r{r}']['info']['overlap_vs_f16_worst'])}" for r in below
        )
        return (
            f"64 is the smallest rank that did ({miss}), {cost}; 128 costs more time and memory for no gain "
            "here."
        )
    if min(ok) < 64:
        return (
            f"Rank {min(ok)} already did on these smooth scenes; 64 keeps a margin for rougher ones, {cost}."
        )
    return f"Only ranks above 64 did here ({', '.join(map(str, ok))}): the default 64 is {cost}."


def reading(sec: dict) -> list[str]:
    """The text query's part of the reading: the default and why."""
    s = {p["info"]["setting"]: p for p in sec["points"]}
    n, ex = sec["gaussians"], s["f32"]
    bpg = lambda p: p["info"]["bytes_per_gaussian"]  # noqa: E731
    L = [
        "- **Text query: compact rank 64 int8 + exact re-rank of 10k above 200K embedded Gaussians, exact "
        f"below.** At {n:,} Gaussians the exact float32 scan takes {ex['time_ms']:.1f} ms and {bpg(ex):.0f} "
        f"B/Gaussian (the reference's top-100 relevancies span {sec['reference_spread']:.1e} on average: the "
        "scale the relevancy errors below read against)."
    ]
    if "engine" in s:
        d, via = s["engine"], s.get(sec.get("engine_path", ""))
        L.append(
            "  The default point is the product path, SceneEngine.text_query on the exported package with "
            f"the server's EngineConfig: {d['time_ms']:.2f} ms, {bpg(d):.0f} B/Gaussian, top-100 overlap "
            f"error {e(d['errors']['overlap'])} (worst query {e(d['errors']['overlap_worst'])}), max "
            f"relevancy error {e(d['errors']['relevancy'])}"
            + (
                f"; it takes the path of the bare '{via['curve']}: {via['label']}' setting "
                f"({via['time_ms']:.2f} ms)."
                if via
                else "."
            )
        )
    ranks = sec["config"]["ranks"]
    if "r64" in s:
        d, nr = s["r64"], s["r64nr"]
        same = [f"{r}" for r in ranks if s[f"r{r}"]["info"].get("overlap_vs_f16_worst", 1) == 0]
        kept = ", ".join(f"{100 * (1 - s[f'r{r}nr']['errors']['overlap']):.0f}% at rank {r}" for r in ranks)
        L.append(
            f"  Rank 64 with re-rank: {d['time_ms']:.1f} ms ({ex['time_ms'] / d['time_ms']:.0f}x faster), "
            f"{bpg(d):.0f} B/Gaussian ({bpg(ex) / bpg(d):.0f}x less); top-100 overlap error "
            f"{e(d['errors']['overlap'])} (worst query {e(d['errors']['overlap_worst'])}) and max relevancy "
            f"error {e(d['errors']['relevancy'])} against float32, "
            f"{e(d['info'].get('overlap_vs_f16', float('nan')))} against the exact scores of the float16 "
            "values it re-ranks from. Without the re-rank the same scan loses "
            f"{pct(nr['errors']['overlap'])} of the top-100 (max relevancy error "
            f"{e(nr['errors']['relevancy'])}). Ranks whose re-ranked top-100 equalled the float16 exact one "
            f"in every query: {', '.join(same) or 'none'}. The compact scores alone keep {kept} of the exact "
            "top-100 (how deep the true top-100 sit among the 10k candidates). " + rank_choice(s, ranks)
        )
    f16, f16c = s["f16as32"], s["f16"]
    if f16["errors"]["overlap"] > 0:
        L.append(
            f"  Float16 storage itself changes the top-100 set: {pct(f16['errors']['overlap'])} of it on "
            f"average, {pct(f16['errors']['overlap_worst'])} in the worst query (near ties at the 100th "
            "place); every path that reads a package, compact or exact, inherits this."
        )
    L.append(
        "  Below 200K the engine holds the package's float16 values as float32 (max relevancy error "
        f"{e(f16['errors']['relevancy'])}, {f16['time_ms']:.1f} ms, as fast as float32); keeping them as "
        f"float16 and widening chunk by chunk halves the memory but took {f16c['time_ms']:.1f} ms "
        f"({f16c['time_ms'] / ex['time_ms']:.1f}x the float32 scan: torch widens float16 slowly on this CPU)."
    )
    subs = [p for p in sec["points"] if p["curve"].startswith("most opaque")]
    if subs:
        worst = max(subs, key=lambda p: float(p["label"].rstrip("%")))
        saved = 1 - float(worst["label"].rstrip("%")) / 100
        L.append(
            f"  Ranking only the most opaque Gaussians is not a default: even the top {worst['label']} miss "
            f"{pct(worst['errors']['overlap'])} of the exact top-100 to save {saved:.0%} of the scan "
            "(opacity says nothing about meaning; the field's own selection, opacity > 0.25 and a projected "
            "radius > 2 px, is applied before any of this)."
        )
    return L


def plot(sec: dict, path: Path, stamp: str) -> None:
    plot_work_precision(
        sec["points"],
        [("overlap", "1 - top-100 overlap (mean over queries)"), ("relevancy", "max relevancy error")],
        path,
        f"Text query: error against time ({sec['gaussians']:,} Gaussians, D={D})",
        stamp,
    )
