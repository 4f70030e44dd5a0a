"""Pose query section: the relevancy image of a camera, every speed knob (channel path, backend,
resolution, tile size, compact dots) against the full-channel render on the reference backend, and the
default measured through the product path (render_pose on a SceneEngine opened from an exported package)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import D, canonical_vectors, fieldlike, make_queries, med_ms
from benchmarks.workprec.engine import product_engine
from benchmarks.workprec.measure import GPU_NOTE, Point, e, image_error, interleaved, pct
from benchmarks.workprec.plots import plot_work_precision
from benchmarks.workprec.sizes import PoseSizes


def p90_ms(ts) -> float:
    """90th percentile of times in seconds, in milliseconds."""
    return float(np.percentile(ts, 90) * 1e3)


def render_scene(name: str, width: int, height: int):
    """(means, quats, scales, opacities, camera) as benchmarks/raster.py renders them (benchmarks/scenes.py
    ``view``)."""
    from benchmarks.scenes import view

    return view(name, width, height)


def upsample(img: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """[h,w,C] -> [height,width,C] bilinear (pixel centres aligned, as a resized camera's are)."""
    x = img.permute(2, 0, 1)[None]
    return torch.nn.functional.interpolate(x, (height, width), mode="bilinear", align_corners=False)[
        0
    ].permute(1, 2, 0)


@dataclass(frozen=True)
class PoseSetting:
    """One way to produce a relevancy image."""

    backend: str = "cpu"
    """Rasteriser backend."""
    full_channels: bool = False
    """Render all D embedding channels and score the rendered feature (else dot-then-render, 5 channels)."""
    scale: float = 1.0
    """Render at this fraction of the size, then upsample the channels bilinearly."""
    tile: int = 16
    """Tile edge of the rasteriser."""
    compact: bool = False
    """Dots from the compact index (int8, rank 64) instead of the exact float32 embeddings."""


def relevancy_image(
    setting: PoseSetting, geom: tuple, cam, emb: torch.Tensor, canon: torch.Tensor, cd: torch.Tensor, index, q
) -> torch.Tensor:
    """[H,W] relevancy of query q for ``setting`` (geom: means, quats, scales, opacities)."""
    from fmgs.query.relevancy import TEMPERATURE, relevancy
    from fmgs.render import RasterConfig, rasterize

    rc = RasterConfig(tile_size=setting.tile)
    c = cam if setting.scale == 1 else cam.scaled(setting.scale)
    if setting.full_channels:
        F = rasterize(*geom, emb, c, config=rc, backend=setting.backend).image
        img = torch.cat([(F @ q)[..., None], F @ canon.T], -1)
    else:
        dots = index.dots(q[None]) if setting.compact else (emb @ q)[:, None]
        img = rasterize(*geom, torch.cat([dots, cd], 1), c, config=rc, backend=setting.backend).image
    if setting.scale != 1:
        img = upsample(img, cam.height, cam.width)
    return relevancy(img[..., 0], img[..., 1:], TEMPERATURE)


POSE_SETTINGS: dict[str, tuple[PoseSetting, tuple[str, ...]]] = {
    # name: (setting, curves it belongs to); the knobs vary "dtr/cpu": dot-then-render, cpu, full size,
    # tile 16, exact float32 dots (the engine's path, from the bare arrays)
    "full/reference": (
        PoseSetting("reference", True),
        ("channel path (reference)", "backend (full channels)"),
    ),
    "full/cpu": (PoseSetting("cpu", True), ("channel path (cpu)", "backend (full channels)")),
    "dtr/reference": (PoseSetting("reference"), ("channel path (reference)", "backend (dot-then-render)")),
    "dtr/cpu": (
        PoseSetting(),
        ("channel path (cpu)", "backend (dot-then-render)", "resolution scale", "tile size", "index dots"),
    ),
    "scale 0.5": (PoseSetting(scale=0.5), ("resolution scale",)),
    "scale 0.25": (PoseSetting(scale=0.25), ("resolution scale",)),
    "tile 8": (PoseSetting(tile=8), ("tile size",)),
    "tile 32": (PoseSetting(tile=32), ("tile size",)),
    "compact dots": (PoseSetting(compact=True), ("index dots",)),
}
POSE_LABELS = {
    "full/reference": "full channels, reference backend (exact)",
    "full/cpu": "full channels, cpu",
    "dtr/reference": "dot-then-render, reference",
    "dtr/cpu": "dot-then-render, cpu, x1, tile 16, exact dots",
    "scale 0.5": "x0.5 + bilinear",
    "scale 0.25": "x0.25 + bilinear",
    "tile 8": "tile 8",
    "tile 32": "tile 32",
    "compact dots": "int8 rank-64 dots",
}


ENGINE = "engine"
"""The default setting: the product path."""
ENGINE_CURVE = "product path"
SHARDS = (2, 4, 8)
"""Spatial shard counts of the package whose composited renders are measured (fmgs.query.sharded)."""
SHARD_CURVE = "shards (layers composited front to back)"


def engine_image(engine, cam, q: torch.Tensor) -> torch.Tensor:
    """[H,W] relevancy of query q through the product path."""
    from fmgs.query.pose import render_pose

    return render_pose(engine, cam, q, ("relevancy",)).relevancy


def image_errors(outs: list[torch.Tensor], refs: list[torch.Tensor]) -> dict[str, float]:
    """The section's error measures of images against the reference images, over the queries."""
    errs = [image_error(o, r) for o, r in zip(outs, refs, strict=True)]
    return {
        "max": max(x.max_abs for x in errs),
        "mean": float(np.mean([x.mean_abs for x in errs])),
        "argmax_disagree": 1.0 - float(np.mean([x.argmax_same for x in errs])),
        "argmax_px": float(np.mean([x.argmax_px for x in errs])),
    }


@torch.no_grad()
def section(sz: PoseSizes, work: Path) -> dict:
    from fmgs.gaussians import GaussianSet
    from fmgs.query.index import EmbeddingIndex, IndexConfig
    from fmgs.query.relevancy import TEMPERATURE, relevancy
    from fmgs.render import rasterize

    means, quats, scales, opac, cam = render_scene(sz.scene, sz.width, sz.height)
    geom = (means, quats, scales, opac)
    emb = fieldlike(means)
    canon = canonical_vectors()
    cd = emb @ canon.T
    queries = make_queries(emb, sz.queries)
    index = EmbeddingIndex.build(emb, cd, IndexConfig(rank=64, exact_below=0))
    # The product path: this geometry and these embeddings exported as a package, opened as the server
    # does. Its channel cache is off, so every image pays for its dots as a new text does.
    engine = product_engine(work / "pose-package", GaussianSet.from_activated(*geom), emb, canon)
    engine.CHANNEL_CACHE = 0
    # The reference: the full D-channel render on the reference backend, then scored per pixel.
    F = rasterize(*geom, emb, cam, backend="reference").image
    refs = [relevancy(F @ q, F @ canon.T, TEMPERATURE) for q in queries]
    spread = float(np.mean([float(r.max() - r.min()) for r in refs]))
    by_set = query_set_points(sz, work, geom, cam, emb, canon, cd, F)
    del F
    fns = {
        name: (lambda i, s=s: relevancy_image(s, geom, cam, emb, canon, cd, index, queries[i]))
        for name, (s, _) in POSE_SETTINGS.items()
    }
    fns[ENGINE] = lambda i: engine_image(engine, cam, queries[i])
    # The same package split into k spatial shards, every shard's layer rendered here one after another
    # (the work of a sharded render; on a cluster the layers render in parallel).
    from fmgs.query.sharded import ShardedSceneEngine
    from fmgs.scene.shards import write_shards

    for k in SHARDS:
        sharded = ShardedSceneEngine(write_shards(work / "pose-package", work / f"pose-shards-{k}", k))
        for shard in sharded.engines:
            shard.CHANNEL_CACHE = 0
        fns[f"shards {k}"] = lambda i, sh=sharded: sh.render_pose(cam, queries[i]).relevancy
    times, outs = interleaved(fns, len(queries), sz.reps)
    points = []
    for name, (s, curves) in POSE_SETTINGS.items():
        errs = image_errors(outs[name], refs)
        for curve in curves:
            points.append(
                Point(
                    curve,
                    POSE_LABELS[name],
                    med_ms(times[name]),
                    errs,
                    exact=name == "full/reference",
                    info={
                        "setting": name,
                        **asdict(s),
                        "p90_ms": p90_ms(times[name]),
                    },
                )
            )
    dots = "exact" if engine.index.exact else f"int8 rank-{engine.index.cfg.rank}"
    points.append(
        Point(
            ENGINE_CURVE,
            f"SceneEngine render_pose ({dots} dots of the float16 package)",
            med_ms(times[ENGINE]),
            image_errors(outs[ENGINE], refs),
            default=True,
            info={
                "setting": ENGINE,
                "backend": engine.cfg.backend,
                "compact": not engine.index.exact,
                "p90_ms": p90_ms(times[ENGINE]),
            },
        )
    )
    for k in SHARDS:
        name = f"shards {k}"
        points.append(
            Point(
                SHARD_CURVE,
                f"{k} shards, composited",
                med_ms(times[name]),
                image_errors(outs[name], refs),
                info={"setting": name, "shards": k, "p90_ms": p90_ms(times[name])},
            )
        )
    return {
        "config": asdict(sz),
        "gaussians": int(means.shape[0]),
        "reference_spread": spread,
        "points": [asdict(p) for p in points],
        "query_sets": by_set,
    }


QUERY_SETS = ("near", "typical", "clip", "absent")
"""benchmarks/query_sets.py's sets the compact path is measured on (ties: near, with exact copies)."""


def query_set_points(sz: PoseSizes, work: Path, geom, cam, emb, canon, cd, F) -> dict[str, dict]:
    """Per query set: the relevancy image coloured by the compact int8 rank-64 scores (what the engine
    rendered on its compact path before), and the engine's compact path as it runs now (exact dots of the
    Gaussians the view touches), both against the full-channel reference F [H,W,D]; the engine's time for a
    new text (its channel cache off) and for a frame of a pose stream (the text cached)."""
    from dataclasses import replace

    from benchmarks.query_sets import query_sets
    from benchmarks.workprec.engine import server_engine_config
    from fmgs.query.engine import SceneEngine
    from fmgs.query.index import EmbeddingIndex, IndexConfig
    from fmgs.query.relevancy import TEMPERATURE, relevancy

    sets = query_sets(emb, torch.zeros(0, dtype=torch.int64), sz.queries)
    index = EmbeddingIndex.build(emb, cd, IndexConfig(rank=64, exact_below=0))
    # The compact path as a 200K+ scene takes it (exact_below=0 forces it on this scene's size).
    cfg = server_engine_config()
    new_text = SceneEngine.open(work / "pose-package", replace(cfg, index=replace(cfg.index, exact_below=0)))
    new_text.CHANNEL_CACHE = 0
    stream = SceneEngine.open(work / "pose-package", new_text.cfg)
    int8 = PoseSetting(compact=True)
    out = {}
    for name in QUERY_SETS:
        qs = sets[name]
        refs = [relevancy(F @ q, F @ canon.T, TEMPERATURE) for q in qs]
        for q in qs:
            engine_image(stream, cam, q)  # the stream's first frame: the rest of its frames are cached
        fns = {
            "int8": lambda i, qs=qs: relevancy_image(int8, geom, cam, emb, canon, cd, index, qs[i]),
            "new text": lambda i, qs=qs: engine_image(new_text, cam, qs[i]),
            "stream frame": lambda i, qs=qs: engine_image(stream, cam, qs[i]),
        }
        times, outs = interleaved(fns, len(qs), sz.reps)
        best = float((emb @ qs.T).amax(0).median())
        out[name] = {
            "best_cosine": best,
            "spread": float(np.mean([float(r.max() - r.min()) for r in refs])),
            **{k: {"ms": med_ms(times[k]), "errors": image_errors(outs[k], refs)} for k in fns},
        }
    return out


def query_set_table(by_set: dict[str, dict]) -> list[str]:
    """The per-query-set table of REPORT.md's pose section."""
    L = [
        "",
        "Every query set of benchmarks/query_sets.py (near: a scene embedding and a little noise; typical: "
        "more noise; CLIP-like: cosine 0.2-0.35 with one embedding; absent: random directions), the same "
        "package on the compact path (`exact_below=0`: what a scene of 200K+ embedded Gaussians takes). "
        "Before: the image coloured by the compact int8 rank-64 scores. Now: the engine scores exactly the "
        "Gaussians the view touches (`fmgs.render.visible`; float64 dots of the float16 embeddings, rounded "
        "once), the compact scores never colour a pixel. Times: a new text (channel cache off: every image "
        "scores its view) and a frame of a pose stream (the text cached: only rows no earlier frame "
        "touched). Both are measured against the reference above, rendered from the float32 embeddings; the "
        "package stores float16, which is the whole of the exact colours' error here "
        "(tests/query/test_pose.py holds them to 1e-4 of a float64 dot-then-render of the stored values at "
        "1M Gaussians).",
        "",
        "| query set | best cos | relevancy spread | int8 colours: max / mean error, argmax moved | ms | "
        "exact colours (now): max / mean error, argmax moved | ms, new text | ms, stream frame |",
        "|---|---:|---:|---|---:|---|---:|---:|",
    ]
    for name, r in by_set.items():
        a, b = r["int8"]["errors"], r["new text"]["errors"]
        L.append(
            f"| {name} | {r['best_cosine']:.2f} | {r['spread']:.3f} | {e(a['max'])} / {e(a['mean'])}, "
            f"{pct(a['argmax_disagree'])} | {r['int8']['ms']:.0f} | {e(b['max'])} / {e(b['mean'])}, "
            f"{pct(b['argmax_disagree'])} | {r['new text']['ms']:.0f} | {r['stream frame']['ms']:.0f} |"
        )
    return L


def by_setting(points: list[dict]) -> dict[str, dict]:
    """One point per setting (a setting can lie on several curves)."""
    out: dict[str, dict] = {}
    for p in points:
        key = p["info"].get("setting", f"{p['curve']}/{p['label']}")
        out.setdefault(key, {**p, "curves": []})["curves"].append(p["curve"])
    return out


def markdown(sec: dict, img: str) -> list[str]:
    """The section's text and table in REPORT.md."""
    cfg = sec["config"]
    L = [
        "## 2. Pose query (relevancy image)",
        "",
        f"Scene: {cfg['scene']} ({sec['gaussians']:,} Gaussians, all embedded, field-like D = {D} "
        f"embeddings), {cfg['width']}x{cfg['height']}, {cfg['queries']} queries x {cfg['reps']} passes. "
        f"Reference: the full {D}-channel feature image rendered on the reference backend, then f.q and "
        "f.c_n per pixel and the relevancy (render_pose_reference-style). Errors over all pixels at full "
        "size: max and mean |relevancy difference|, and the share of queries whose most relevant pixel "
        "moved. Lower resolutions render the 5 channels at x0.5 / x0.25 and upsample them bilinearly "
        "before scoring. The reference images' relevancy spans "
        f"{sec.get('reference_spread', float('nan')):.3f} (max - min, mean over queries)."
        + (
            ' The default point is the product path: `render_pose(engine, camera, q, ("relevancy",))` '
            "on a SceneEngine opened with the query server's `EngineConfig` from a package exported with "
            "this geometry and these embeddings (float16 values, canonical dots from them), its channel "
            "cache off so every image pays for its dots; every other setting is an alternative computed "
            "from the bare float32 arrays."
            if any(p["info"].get("setting") == ENGINE for p in sec["points"])
            else ""
        ),
        "",
        f"![pose query work-precision]({img})",
        "",
        "| setting | on curves | median ms | max error | mean error | argmax moved (queries / mean px) | "
        "GPU |",
        "|---|---|---:|---:|---:|---:|---|",
    ]
    for p in by_setting(sec["points"]).values():
        flags = (" **(exact reference)**" if p["exact"] else "") + (" **(default)**" if p["default"] else "")
        L.append(
            f"| {p['label']}{flags} | {', '.join(p['curves'])} | {p['time_ms']:.1f} | "
            f"{e(p['errors']['max'])} | {e(p['errors']['mean'])} | {pct(p['errors']['argmax_disagree'])} / "
            f"{p['errors'].get('argmax_px', float('nan')):.1f} | {GPU_NOTE} |"
        )
    if "query_sets" in sec:
        L += query_set_table(sec["query_sets"])
    return L


def _reading(sec: dict) -> list[str]:
    """The pose query's part of the reading: the default and why."""
    s = {p["info"]["setting"]: p for p in sec["points"]}
    ref, dc, dr, fc = s["full/reference"], s["dtr/cpu"], s["dtr/reference"], s["full/cpu"]
    t8, t32, h, q = s["tile 8"], s["tile 32"], s["scale 0.5"], s["compact dots"]

    def rel(p: dict) -> str:
        x = 100 * (p["time_ms"] / dc["time_ms"] - 1)
        return f"{abs(x):.0f}% {'less' if x < 0 else 'more'} time"

    px = lambda p: p["errors"].get("argmax_px", float("nan"))  # noqa: E731
    eng = s.get(ENGINE)
    via = (
        f"Through the product path (SceneEngine.render_pose, the server's EngineConfig; the default point) "
        f"an image takes {eng['time_ms']:.0f} ms ({rel(eng)} than the same path from the bare float32 "
        f"arrays) with max error {e(eng['errors']['max'])} and the argmax moved in "
        f"{pct(eng['errors']['argmax_disagree'])} of the "
        "queries: the package's float16 embeddings and its stored geometry (log scales, opacity logits). "
        if eng
        else ""
    )
    return [
        "- **Pose query: dot-then-render on the cpu backend, full size, tile 16.** "
        + via
        + "With float32 dots, dot-then-render equals "
        f"the full {D}-channel render up to float32 rounding (max error {e(dc['errors']['max'])}, against a "
        f"relevancy spread of {sec['reference_spread']:.3f} per image) and takes {dc['time_ms']:.0f} ms, "
        f"against {fc['time_ms']:.0f} ms for all channels on the same backend and {ref['time_ms']:.0f} ms "
        f"for the reference; the reference backend with 5 channels takes {dr['time_ms']:.0f} ms. Tiles of 8 "
        f"and 32 give the same image (max error {e(t8['errors']['max'])} / {e(t32['errors']['max'])}) in "
        f"{rel(t8)} / {rel(t32)} than tile 16 (the tile size changes the binning, never the image; 16 stays, "
        "one run of a few repetitions on a shared machine does not separate 16 from 32). Half resolution "
        f"takes {rel(h)} but moves the most relevant pixel in {pct(h['errors']['argmax_disagree'])} of the "
        f"queries, by {px(h):.1f} px on average (max error {e(h['errors']['max'])}): a client that can live "
        "with that asks for a smaller image. The int8 rank-64 dots (the compact state of scenes of 200K+ "
        f"embedded Gaussians) would change the relevancy by up to {e(q['errors']['max'])} on these queries "
        f"and move the argmax in {pct(q['errors']['argmax_disagree'])} of them, for {rel(q)}"
        + _sets_reading(sec)
    ]


def _sets_reading(sec: dict) -> str:
    """The compact path's sentence: int8 colours against exact ones on every query set."""
    by = sec.get("query_sets")
    if not by:
        return "."
    worst = max(by, key=lambda n: by[n]["int8"]["errors"]["max"])
    exact_max = max(r["new text"]["errors"]["max"] for r in by.values())
    new_ms = [r["new text"]["ms"] for r in by.values()]
    old_ms = [r["int8"]["ms"] for r in by.values()]
    frame = [r["stream frame"]["ms"] for r in by.values()]
    return (
        f"; over every query set, up to {e(by[worst]['int8']['errors']['max'])} (on {worst} queries, table "
        "below). So the compact scores no longer colour an image: the engine scores "
        f"exactly the Gaussians the view touches, max error {e(exact_max)} on every query set, at "
        f"{min(new_ms):.0f}-{max(new_ms):.0f} ms for a new text against {min(old_ms):.0f}-{max(old_ms):.0f} "
        f"ms with int8 colours, and {min(frame):.0f}-{max(frame):.0f} ms for a frame of a pose stream."
    )


def plot(sec: dict, path: Path, stamp: str) -> None:
    c = sec["config"]
    plot_work_precision(
        sec["points"],
        [
            ("max", "max relevancy error"),
            ("mean", "mean relevancy error"),
            ("argmax_disagree", "argmax moved"),
        ],
        path,
        f"Pose query: error against time ({c['scene']}, {c['width']}x{c['height']})",
        stamp,
        xlabel="median time per relevancy image (ms)",
        by_time=True,
    )


def reading(sec: dict) -> list[str]:
    """The pose query's part of the reading, with the sharded renders when they were measured."""
    out = _reading(sec)
    s = {p["info"]["setting"]: p for p in sec["points"]}
    shards = [s[f"shards {k}"] for k in SHARDS if f"shards {k}" in s]
    if shards:
        parts = ", ".join(
            f"{p['info']['shards']} shards: mean {e(p['errors']['mean'])}, max {e(p['errors']['max'])}, "
            f"argmax moved in {pct(p['errors']['argmax_disagree'])}, {p['time_ms']:.0f} ms"
            for p in shards
        )
        out.append(
            "- **Sharded scenes (pose queries on a Ray cluster): each shard renders its own Gaussians' "
            "channels and opacity, the layers are composited front to back in the k-d order for the "
            f"camera.** Against the reference: {parts} (all layers rendered one after another here; on a "
            "cluster they render in parallel). The difference comes from Gaussians that straddle a split "
            "plane, blended in their cell's place rather than their depth's, and from the early stop no "
            "longer seeing the other cells' opacity."
        )
    return out
