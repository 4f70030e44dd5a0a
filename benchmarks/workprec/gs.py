"""3DGS training section: held-out quality of the synthetic labelled scene against training time, one
fit per step count (the fits are reused by the field section)."""

from __future__ import annotations

import json
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import NamedTuple

import torch

from benchmarks.workprec.measure import GPU_NOTE, Point
from benchmarks.workprec.plots import figure, save
from benchmarks.workprec.sizes import GSSizes, SceneSizes


class GSFit(NamedTuple):
    """A 3DGS fit of the synthetic scene."""

    ply: Path
    steps: int
    cpu_seconds: float
    """CPU time of the training process (one thread: the wall time on an idle core)."""
    wall_seconds: float
    """Wall time of the optimisation loop (depends on what else the machine runs)."""
    gaussians: int


def synth_scene(work: Path, sz: SceneSizes) -> Path:
    """The labelled synthetic scene (fmgs synth), generated once per work folder."""
    from fmgs.synth import SynthConfig, generate

    data = work / f"scene-{sz.width}x{sz.height}-{sz.views}"
    if not (data / "scene.json").is_file():
        generate(data, SynthConfig(views=sz.views, width=sz.width, height=sz.height, points=sz.points))
    return data


def gs_fit(work: Path, data: Path, sz: SceneSizes, steps: int) -> GSFit:
    """Train 3DGS for ``steps`` (the 30K schedule compressed to it); reused when the work folder has it."""
    from fmgs.data.dataset import load_dataset
    from fmgs.train.gaussians import GSTrainConfig, train_gaussians

    out = work / f"{data.name}-gs-{steps}"
    meta = out / "fit.json"
    cfg = GSTrainConfig.reduced(steps, max_init_points=sz.init_points)
    densify = replace(cfg.densify, grad_threshold=sz.grad_threshold, max_gaussians=sz.max_gaussians)
    cfg = replace(cfg, densify=densify)
    key = json.loads(json.dumps(asdict(cfg))) | {"threads": torch.get_num_threads()}
    if meta.is_file() and json.loads(meta.read_text())["config"] == key:
        m = json.loads(meta.read_text())
        return GSFit(out / "point_cloud.ply", steps, m["cpu_seconds"], m["wall_seconds"], m["gaussians"])
    ds = load_dataset(data)
    warm = replace(GSTrainConfig.reduced(3, max_init_points=sz.init_points), densify=densify)
    train_gaussians(ds, work / "warm-up-gs", warm, progress=False, resume=False)  # compiled kernels, caches
    torch.manual_seed(0)
    c0 = time.process_time()
    r = train_gaussians(ds, out, cfg, progress=False, resume=False)
    fit = GSFit(out / "point_cloud.ply", steps, time.process_time() - c0, r.seconds, r.gaussians.num)
    meta.write_text(
        json.dumps(
            {
                "config": key,
                "cpu_seconds": fit.cpu_seconds,
                "wall_seconds": r.seconds,
                "gaussians": fit.gaussians,
            }
        )
    )
    return fit


def section(sz: GSSizes, scene: SceneSizes, work: Path) -> dict:
    from fmgs.data.dataset import load_dataset
    from fmgs.io.ply import read_ply
    from fmgs.train.evaluate import evaluate
    from fmgs.train.gaussians import trained_background

    data = synth_scene(work, scene)
    ds = load_dataset(data)
    points = []
    for steps in sz.steps:
        fit = gs_fit(work, data, scene, steps)
        ev = evaluate(read_ply(fit.ply), ds, background=trained_background(fit.ply.parent, ds))
        points.append(
            Point(
                "training steps",
                f"{steps}",
                fit.cpu_seconds * 1e3,
                {"dssim": 1.0 - ev.ssim},
                info={
                    "steps": steps,
                    "psnr": ev.psnr,
                    "ssim": ev.ssim,
                    "gaussians": fit.gaussians,
                    "wall_seconds": fit.wall_seconds,
                },
            )
        )
    return {"config": asdict(sz), "scene": asdict(scene), "points": [asdict(p) for p in points]}


def markdown(sec: dict, img: str) -> list[str]:
    """The section's text and table in REPORT.md."""
    s = sec["scene"]
    L = [
        "## 4. 3DGS training",
        "",
        f"Scene: `fmgs synth` ({s['views']} views, {s['width']}x{s['height']}), initialised from "
        f"{s['init_points']:,} of its surface samples; the 30K-step schedule compressed to each step count "
        f"(densification threshold {s['grad_threshold']}, at most {s['max_gaussians']:,} Gaussians), CPU "
        "reference backend. Held-out views: every 8th. Time: CPU seconds of the training call on one "
        "thread, one run per step count (wall time of the loop beside it).",
        "",
        f"![3DGS quality against time]({img})",
        "",
        "| steps | train CPU s (wall s) | Gaussians | held-out PSNR | SSIM | GPU |",
        "|---:|---:|---:|---:|---:|---|",
    ]
    for p in sec["points"]:
        i = p["info"]
        L.append(
            f"| {i['steps']} | {p['time_ms'] / 1e3:.1f} ({i['wall_seconds']:.1f}) | {i['gaussians']:,} | "
            f"{i['psnr']:.2f} dB | {i['ssim']:.3f} | {GPU_NOTE} |"
        )
    return L


def reading(sec: dict) -> list[str]:
    """The 3DGS part of the reading."""
    pts = sorted(sec["points"], key=lambda p: p["info"]["steps"])
    return [
        "- **3DGS:** held-out PSNR "
        + ", ".join(
            f"{p['info']['psnr']:.1f} dB after {p['label']} steps ({p['time_ms'] / 1e3:.0f} s)" for p in pts
        )
        + "; the default stays graphdeco's 30K steps (a GPU-sized job, not run on this CPU)."
    ]


def plot(sec: dict, path: Path, stamp: str) -> None:
    plt, fig, axes = figure(2)
    pts = sorted(sec["points"], key=lambda p: p["time_ms"])
    x = [p["time_ms"] / 1e3 for p in pts]
    for ax, ys, label in (
        (axes[0], [p["info"]["psnr"] for p in pts], "held-out PSNR (dB, higher is better)"),
        (axes[1], [p["errors"]["dssim"] for p in pts], "1 - SSIM (held-out)"),
    ):
        ax.plot(x, ys, "o-", label="training steps")
        for p, xi, yi in zip(pts, x, ys, strict=True):
            ax.annotate(
                f"{p['label']} steps", (xi, yi), fontsize=7, xytext=(3, 3), textcoords="offset points"
            )
        ax.set_xscale("log")
        ax.set_xlabel("training CPU time (s, one thread)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    save(plt, fig, path, "3DGS: held-out quality against training time", stamp)
