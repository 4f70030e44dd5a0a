"""3DGS quality and time: train, evaluate on held-out views, and report.

    python -m benchmarks.gs run DATA OUT [--steps N] [--scale S] [--grad-threshold T]  # train + eval
    python -m benchmarks.gs synth OUT [--views 48] [--size 128x96]                       # make a scene
    python -m benchmarks.gs report OUT [OUT ...]                                         # -> GS.md

A run folder holds train.json (fmgs train-gs) and eval/eval.json (fmgs eval-gs); the report reads only those.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from benchmarks.common import RESULTS, machine, machine_words


def run(args) -> None:
    from fmgs.cli import main as fmgs

    out = Path(args.out)
    cmd = [
        "train-gs",
        args.data,
        "--out",
        str(out),
        "--steps",
        str(args.steps),
        "--scale",
        str(args.scale),
        "--restart",
    ]
    if args.grad_threshold is not None:
        cmd += ["--grad-threshold", str(args.grad_threshold)]
    assert fmgs(cmd) == 0
    assert (
        fmgs(
            [
                "eval-gs",
                args.data,
                str(out / "point_cloud.ply"),
                "--out",
                str(out / "eval"),
                "--scale",
                str(args.scale),
            ]
        )
        == 0
    )
    (out / "data.txt").write_text(str(args.data))


def report(args) -> None:
    info = machine()
    lines = [
        "# 3DGS training: held-out quality against time",
        "",
        f"Reported {info['date']} from runs on {machine_words(info)}.",
        "Every 8th image is held out (never trained on); PSNR/SSIM are means over those views at the "
        "training resolution. Regenerate: `python -m benchmarks.gs run DATA OUT ...`, then `report OUT ...`.",
        "",
        "| dataset | views (train/held-out) | image size | steps | grad threshold | Gaussians | train time "
        "| held-out PSNR | SSIM | backend |",
        "|---|---:|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for d in args.runs:
        d = Path(d)
        t = json.loads((d / "train.json").read_text())
        e = json.loads((d / "eval" / "eval.json").read_text())
        e["psnr"] = float(e["psnr"])  # eval.json writes an exact view's +inf as "inf" (strict JSON)
        data = (d / "data.txt").read_text().strip() if (d / "data.txt").is_file() else "?"
        cfg = t["config"]
        size, views = f"scale {cfg['image_scale']}", "?"
        if Path(data).exists():
            from fmgs.data.dataset import load_dataset

            ds = load_dataset(data)
            cam = ds.frames[0].camera.scaled(cfg["image_scale"])
            size = f"{cam.width}x{cam.height}"
            train, held = ds.split(cfg["holdout_every"])
            views = f"{len(train)}/{len(held)}"
        lines.append(
            f"| {Path(data).name} | {views} | {size} | {t['steps']} | {cfg['densify']['grad_threshold']:g} "
            f"| {t['gaussians']:,} | {t['seconds'] / 60:.1f} min | **{e['psnr']:.2f} dB** | {e['ssim']:.3f} "
            f"| {t.get('backend', cfg['backend'])} |"
        )
    out = RESULTS / "GS.md"
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def synth(args) -> None:
    from fmgs.synth import SynthConfig, generate

    w, h = (int(v) for v in args.size.split("x"))
    generate(args.out, SynthConfig(views=args.views, width=w, height=h, objects=6, seed=0))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("data")
    r.add_argument("out")
    r.add_argument("--steps", type=int, default=2500)
    r.add_argument("--scale", type=float, default=0.25)
    r.add_argument("--grad-threshold", type=float)
    r.set_defaults(func=run)
    s = sub.add_parser("synth")
    s.add_argument("out")
    s.add_argument("--views", type=int, default=48)
    s.add_argument("--size", default="128x96")
    s.set_defaults(func=synth)
    p = sub.add_parser("report")
    p.add_argument("runs", nargs="+")
    p.set_defaults(func=report)
    args = ap.parse_args()
    args.func(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
