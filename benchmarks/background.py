"""An undeclared backdrop: what 3DGS training makes of a constant sky the dataset does not declare.

Generates one tabletop scene with ``fmgs synth --rig grazing`` (every third camera on a low ring whose
images are half backdrop) twice, its backdrop colour declared in transforms.json and not, then trains
3DGS with the same settings three ways: declared (the colour given), learned (undeclared: the trainer's
default, a colour learned with the scene from the images' commonest border colour) and black (undeclared,
``learn_background=False``: what training did before). Scores every held-out view with the colour the run
trained with. Writes benchmarks/results/BACKGROUND.md and BACKGROUND.json.

    python -m benchmarks.background                      # 48 views, 96x72, 3,000 steps (FIELD.md's sizes)
    python -m benchmarks.background --quick --out DIR    # 24 views, 64x48, 300 steps
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from dataclasses import replace
from pathlib import Path

from benchmarks.common import RESULTS, machine, machine_words

RUNS = (("declared", "declared", True), ("learned", "undeclared", True), ("black", "undeclared", False))
"""(run, dataset, learn_background)."""


def measure(views: int, size: str, steps: int, seed: int, work: Path) -> dict:
    from fmgs.data.dataset import load_dataset
    from fmgs.synth import BACKGROUND, SynthConfig, generate
    from fmgs.train.config import GSTrainConfig
    from fmgs.train.evaluate import evaluate
    from fmgs.train.gaussians import train_gaussians

    w, h = (int(v) for v in size.split("x"))
    for tag, declare in (("declared", True), ("undeclared", False)):
        scene = SynthConfig(views=views, width=w, height=h, rig="grazing", seed=seed)
        generate(work / tag, replace(scene, declare_background=declare))
    rows = {}
    for run, data, learn in RUNS:
        ds = load_dataset(work / data)
        base = GSTrainConfig.reduced(steps, seed=0)
        # FIELD.md's reduced settings: a higher densification threshold for short low-resolution runs.
        cfg = replace(base, densify=replace(base.densify, grad_threshold=1e-3), learn_background=learn)
        r = train_gaussians(ds, work / f"run-{run}", cfg, progress=False, resume=False)
        ev = evaluate(r.gaussians, ds, background=r.background)
        low = ds.split(8)[1]
        grazing = {ds.frames[i].name for i in low if int(Path(ds.frames[i].name).stem) % 3 == 2}
        rows[run] = {
            "background": [round(x, 4) for x in r.background],
            "source": r.background_source,
            "gaussians": r.gaussians.num,
            "train_s": round(r.seconds, 1),
            "psnr_mean": ev.psnr,
            "ssim_mean": ev.ssim,
            "worst": ev.worst,
            "below_20db": [v["name"] for v in ev.below()],
            "per_view": [{**v, "grazing": v["name"] in grazing} for v in ev.per_view],
        }
        print(run, {k: v for k, v in rows[run].items() if k != "per_view"}, flush=True)
    sizes = {"views": views, "size": size, "steps": steps, "seed": seed}
    return {**sizes, "true_backdrop": BACKGROUND, "runs": rows}


def report(res: dict, info: dict, command: str) -> str:
    runs = res["runs"]
    L = [
        "# An undeclared backdrop: learned, declared, black",
        "",
        f"Machine: {machine_words(info)}; {info['date']}. Scene: `fmgs synth --rig grazing` (seed "
        f"{res['seed']}, {res['views']} views at {res['size']}, every third camera on a low ring whose "
        f"images are half backdrop; backdrop colour {list(res['true_backdrop'])}), 3DGS "
        f"{res['steps']:,} steps (`GSTrainConfig.reduced`, densification threshold 0.001, as FIELD.md), "
        "every 8th view held out and scored with the colour the run trained with. Reproduce: "
        f"`{command}`.",
        "",
        "| run | background | Gaussians | held-out PSNR mean (dB) | worst view (dB) | views below 20 dB | "
        "SSIM mean | train s |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for run, r in runs.items():
        bg = ", ".join(f"{x:.3f}" for x in r["background"])
        L.append(
            f"| {run} | {r['source']} ({bg}) | {r['gaussians']:,} | {r['psnr_mean']:.2f} | "
            f"{r['worst']['psnr']:.2f} ({r['worst']['name']}) | {len(r['below_20db'])} | "
            f"{r['ssim_mean']:.3f} | {r['train_s']:.0f} |"
        )
    d, le = runs["declared"], runs["learned"]
    L += [
        "",
        "Per held-out view (PSNR dB; * the low, grazing ring):",
        "",
        "| view | " + " | ".join(runs) + " |",
        "|---|" + "---:|" * len(runs),
    ]
    for i, v in enumerate(d["per_view"]):
        mark = " *" if v["grazing"] else ""
        cells = " | ".join(f"{r['per_view'][i]['psnr']:.2f}" for r in runs.values())
        L.append(f"| {v['name']}{mark} | {cells} |")
    gap = le["worst"]["psnr"] - d["worst"]["psnr"]  # positive: the learned run's worst view is better
    count = le["gaussians"] / d["gaussians"] - 1
    L += [
        "",
        "Targets (issue 39): the learned run's worst held-out view at most 1 dB below the declared run's: "
        f"learned minus declared {gap:+.2f} dB ({'met' if gap >= -1 else 'not met'}); Gaussian count within "
        f"20%: {100 * count:+.1f}% ({'met' if abs(count) <= 0.2 else 'not met'}). Not measured here: "
        "textured surroundings (a backdrop that is not one colour); `fmgs synth` renders only a constant "
        "one.",
        "",
    ]
    return "\n".join(L)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=48, help="cameras (default 48)")
    ap.add_argument("--size", default="96x72", help="image size WxH (default 96x72)")
    ap.add_argument("--steps", type=int, default=3000, help="3DGS steps (default 3,000)")
    ap.add_argument("--seed", type=int, default=7, help="scene seed (default 7)")
    ap.add_argument("--quick", action="store_true", help="24 views, 64x48, 300 steps (CI size)")
    ap.add_argument("--out", type=Path, default=RESULTS, help="report folder (default benchmarks/results)")
    a = ap.parse_args(argv)
    if a.quick:
        a.views, a.size, a.steps = 24, "64x48", 300
    work = Path(tempfile.mkdtemp(prefix="fmgs-background-"))
    try:
        res = measure(a.views, a.size, a.steps, a.seed, work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    info = machine()
    res["machine"] = info
    command = "python -m benchmarks.background" + (" --quick" if a.quick else "")
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "BACKGROUND.json").write_text(json.dumps(res, indent=1) + "\n")
    (a.out / "BACKGROUND.md").write_text(report(res, info, command))
    print((a.out / "BACKGROUND.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
