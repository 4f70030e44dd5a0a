"""CLIP target blends section: how well each way of blending the crop pyramid's scales names the object
pixels of generated world scenes before any distillation, against the target time per view it costs, and
what each costs per Gaussian and per query."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

from benchmarks.workprec.measure import GPU_NOTE, Point
from benchmarks.workprec.plots import plot_work_precision
from benchmarks.workprec.sizes import TargetSizes

LERF = "lerf (max over scales)"
"""benchmarks.clip_targets' name of LERF's query-time scale selection."""


def world_scene(work: Path, seed: int, sz: TargetSizes) -> Path:
    """A generated world scene as benchmarks.clip_path makes them (three held-out-name objects)."""
    from benchmarks.clip_path import synth_flags
    from benchmarks.unseen import synth_scene

    data = work / f"world-{seed}-{sz.width}x{sz.height}-{sz.scene_views}"
    return synth_scene(data, seed, sz.scene_views, f"{sz.width}x{sz.height}", synth_flags(seed), "world")


def section(sz: TargetSizes, work: Path) -> dict:
    from benchmarks.clip_targets import REGIONS_DINO, SEGMENTED, rates, target_candidates
    from fmgs.features.pyramid import PyramidConfig
    from fmgs.features.sizes import SCALE_BLEND, SCALE_BLENDS

    seconds: dict[str, float] = {}
    per = [target_candidates(world_scene(work, s, sz), views=sz.views, seconds=seconds) for s in sz.seeds]
    r = rates(per)
    n = seconds["views"]
    ms = {k: 1e3 * v / n for k, v in seconds.items() if k != "views"}
    scales = len(PyramidConfig().scales)
    points = []
    kinds = [(b, "blend", b) for b in SCALE_BLENDS] + [(f"{b} + pooled", "blend + DINO pooling", b) for b in
             SCALE_BLENDS] + [(LERF, "LERF scale selection", "lerf"),
                              (REGIONS_DINO, "region crops (DINO regions)", "regions"),
                              (SEGMENTED, "segments (segmenter stand-in)", "segments")]  # fmt: skip
    for key, curve, label in kinds:
        dino = key not in (LERF, "mean", SEGMENTED)  # the equal mean, LERF and segments use no DINO
        own = ms.get(key, 0.0)
        v = r[key]
        pyramid = 0.0 if key == SEGMENTED else ms["pyramid"]  # segments time their own finest scale
        points.append(
            Point(
                curve,
                label,
                pyramid + (ms["dino"] if dino else 0.0) + own,
                {
                    "object": 1 - v["object_pixels"],
                    "novel": 1 - v["novel_object_pixels"],
                    "miou": 1 - v["miou"],
                },
                default=key == SCALE_BLEND,
                info={
                    "candidate": key,
                    "own_ms": own,
                    "needs_dino": dino,
                    "embeddings_per_gaussian": scales if key == LERF else 1,
                    **v,
                },
            )
        )
    singles = {k: v for k, v in r.items() if k.endswith(" alone")}
    return {
        "config": asdict(sz),
        "scales": scales,
        "pyramid_ms": ms["pyramid"],
        "dino_ms": ms["dino"],
        "single_scales": singles,
        "points": [asdict(p) for p in points],
    }


def markdown(sec: dict, img: str) -> list[str]:
    """The section's text and table in REPORT.md."""
    c = sec["config"]
    L = [
        "## 7. CLIP target blends",
        "",
        "Scenes: `fmgs synth --preset world --objects 10 --novel 3` seeds "
        f"{', '.join(map(str, c['seeds']))} ({c['width']}x{c['height']}, the first {c['views']} of "
        f"{c['scene_views']} views each; the dev scenes the build's default blend was chosen on, no "
        "benchmark seed). Targets: every crop of the hybrid pyramid at the build's defaults through the "
        "CLIP stand-in (`benchmarks/standin`), the DINO stand-in's dense map, then each blend of the "
        "scales (fmgs.features.scale_blend), scored as segmentation is (benchmarks.clip_targets: argmax "
        "over the scene's names but the background, on pixels with geometry). Time: CPU ms per view on "
        "one thread (one pass per view; CPU time leaves out other jobs on the machine): the pyramid "
        f"({sec['pyramid_ms']:.0f} ms), the DINO map ({sec['dino_ms']:.0f} ms) where the blend needs it, "
        "and the blend's own work. The field, the package and query time do not depend on the blend: "
        "every blend writes one embedding per pixel, so the field has one output per Gaussian; LERF's "
        f"max over scales needs one per scale ({sec['scales']}), hence {sec['scales']}x the language bytes "
        "per Gaussian and one scan per scale per text query (not built here: the field has no scale "
        "input). Segments (the build's `--segmenter`, fmgs.features.segment_pool): the finest scale's crops "
        "alone, the segmenter stand-in's segments (`benchmarks/standin_seg`) and the pooling, all in its "
        "own time, since it needs no other scale and no DINO map; one embedding per Gaussian.",
        "",
        f"![CLIP target blends work-precision]({img})",
        "",
        "| targets | needs DINO | CPU ms per view | of which the blend | object pixels | novel-object "
        "pixels | mIoU | embeddings per Gaussian | GPU |",
        "|---|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for p in sec["points"]:
        i = p["info"]
        flag = " **(default)**" if p["default"] else ""
        L.append(
            f"| {i['candidate']}{flag} | {'yes' if i['needs_dino'] else 'no'} | {p['time_ms']:.0f} | "
            f"{i['own_ms']:.1f} | {i['object_pixels']:.3f} | {i['novel_object_pixels']:.3f} | "
            f"{i['miou']:.3f} | {i['embeddings_per_gaussian']} | {GPU_NOTE} |"
        )
    best = max(sec["single_scales"].items(), key=lambda kv: kv[1]["object_pixels"])
    L += [
        "",
        f"For reference, the best single scale ({best[0]}) puts {best[1]['object_pixels']:.3f} of object "
        "pixels nearest their own name.",
    ]
    return L


def reading(sec: dict) -> list[str]:
    """The blends' part of the reading: the default and why."""
    pts = {p["info"]["candidate"]: p for p in sec["points"]}
    d = next(p for p in sec["points"] if p["default"])
    mean = pts["mean"]
    ranked = sorted(sec["points"], key=lambda p: -p["info"]["object_pixels"])
    top = ranked[0]
    text = (
        f"- **CLIP targets: the `{d['info']['candidate']}` blend** (the build's default when a DINO model is "
        f"set). Object pixels nearest their own name before distillation: {d['info']['object_pixels']:.3f} "
        f"against {mean['info']['object_pixels']:.3f} for the paper's equal mean, for "
        f"{d['time_ms'] - mean['time_ms']:.0f} CPU ms more per view ({d['time_ms']:.0f} against "
        f"{mean['time_ms']:.0f} ms, nearly all of it the crop pyramid both share): the DINO map "
        f"({sec['dino_ms']:.0f} ms, which the build computes anyway for the dot-product similarity loss) and "
        f"{d['info']['own_ms']:.1f} ms of weighing and blending against {mean['info']['own_ms']:.1f} ms for "
        "the mean. "
    )
    if top is not d:
        text += (
            f"Here {top['info']['candidate']} names more ({top['info']['object_pixels']:.3f} in "
            f"{top['time_ms']:.0f} ms); the default is judged on the distilled field, where the candidates "
            "are built (CLIP_PATH.md). "
        )
    text += (
        "Bytes per Gaussian and query time are the same for every blend (one embedding per Gaussian); "
        f"LERF's max over scales would take {sec['scales']}x both."
    )
    return [text]


def plot(sec: dict, path: Path, stamp: str) -> None:
    plot_work_precision(
        sec["points"],
        [
            ("object", "1 - object pixels named right"),
            ("novel", "1 - held-out-name pixels"),
            ("miou", "1 - mIoU"),
        ],
        path,
        "CLIP target blends: error against target CPU time per view",
        stamp,
        xlabel="target CPU time per view (ms, one thread)",
        log_error=False,
    )
