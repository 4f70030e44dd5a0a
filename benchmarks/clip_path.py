"""The CLIP-target path on meaning: scenes built with ``--targets clip`` through the full hybrid pyramid
from the CLIP stand-in (fmgs.features.standin, trained into MiniLM's space by scripts/train_standin.py),
side by side with label targets on the same scenes and the same geometry.

    python -m benchmarks.clip_path --out OUT [--seeds 104,105,106] [--report]
    python -m benchmarks.clip_path --out OUT --quick      # a smoke run: one 64x48 scene, short stages

Per unseen seed (no setting and no stand-in training used it): ``fmgs build --targets labels`` at the
defaults (benchmarks.unseen.build_scene), then ``fmgs build --targets clip --clip-model standin:...
--dino-model none --ply`` on that build's 3DGS, each scored on the held-out views as served (2D and 3D
localisation, mIoU, presence), with the stand-in's own crop accuracy on the same held-out views (the
ceiling its targets set). Writes clip_path.json and CLIP_PATH.md (with --report, also into
benchmarks/results/).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import machine, machine_words, save_report
from benchmarks.unseen import PRESENT_KINDS, _quality, build_scene, presence_rates

ROOT = Path(__file__).resolve().parents[1]
STANDIN = ROOT / "benchmarks" / "standin"


def clip_build(out: Path, seed: int, data: Path, standin: Path, field_steps: int | None) -> Path:
    """``fmgs build --targets clip`` with the stand-in on the label build's 3DGS; returns the package."""
    from fmgs.cli import main as fmgs

    ply = out / "models" / ".work" / f"s{seed}" / "gs" / "point_cloud.ply"
    name = f"s{seed}-clip"
    cmd = ["build", str(data), "--name", name, "--models", str(out / "models"), "--targets", "clip",
           "--clip-model", f"standin:{standin}", "--dino-model", "none", "--ply", str(ply)]  # fmt: skip
    if field_steps is not None:
        cmd += ["--field-steps", str(field_steps)]
    t0 = time.perf_counter()
    assert fmgs(cmd) == 0
    (out / f"build-{seed}-clip.json").write_text(
        json.dumps({"seconds": time.perf_counter() - t0, "command": cmd})
    )
    return out / "models" / name


def score(out: Path, seed: int, data: Path, standin: Path) -> dict:
    import torch

    from fmgs.data import HOLDOUT_EVERY
    from fmgs.data.dataset import load_dataset
    from fmgs.features.standin import crop_accuracy, load_standin, sample_crops
    from fmgs.features.text import MiniLMTextEncoder
    from fmgs.query.engine import SceneEngine

    ds = load_dataset(data)
    enc = MiniLMTextEncoder()
    _, test = ds.split(HOLDOUT_EVERY)
    names = json.loads((data / "scene.json").read_text())["label_names"]
    row = {"seed": seed, "views_test": len(test)}
    for kind, pkg in (("labels", f"s{seed}"), ("clip", f"s{seed}-clip")):
        engine = SceneEngine.open(out / "models" / pkg)
        row[kind] = _quality(engine, ds, enc, test, data, names)
        row[kind]["embedded"] = engine.num_embedded
    standin_enc = load_standin(f"standin:{standin}")
    crops, labels = sample_crops(data, 200, np.random.default_rng(seed), standin_enc.image_size, views=test)
    with torch.inference_mode():
        table = enc.encode_text(names)
    row["crop_accuracy"] = crop_accuracy(standin_enc, table, crops, labels, names)
    row["crops"] = len(crops)
    row["build_seconds"] = {
        k: json.loads((out / f"build-{seed}{s}.json").read_text())["seconds"]
        for k, s in (("labels", ""), ("clip", "-clip"))
    }
    return row


def _presence(q: dict) -> tuple[str, str]:
    """(present queries found, absent queries rejected) as "k/n"."""
    sums = [[0, 0], [0, 0]]
    for kind, (ok, n) in presence_rates(q["presence"]).items():
        s = sums[0 if kind in PRESENT_KINDS else 1]
        s[0] += ok
        s[1] += n
    return f"{sums[0][0]}/{sums[0][1]}", f"{sums[1][0]}/{sums[1][1]}"


def report(
    rows: list[dict], info: dict, cmd: str, standin_cfg: dict, knob: list[dict], knob_seed: int
) -> str:
    cfg = standin_cfg
    trained = (
        f"trained into MiniLM's space on crops of {len(cfg['train_seeds'])} other generated scenes "
        f"(`{cfg['command']}`; held-out crop accuracy {cfg['heldout_crop_accuracy']:.3f} on seeds "
        f"{', '.join(map(str, cfg['heldout_seeds']))})"
    )
    lines = [
        "# The CLIP-target path on meaning",
        "",
        f"Measured {info['date']} on {machine_words(info)}, one run of `{cmd}`.",
        "",
        "Each unseen generated scene is built twice on the same 3DGS: with label targets (`--targets "
        "labels`, the names' MiniLM embeddings painted by the label masks) and with CLIP targets "
        "(`--targets clip`: the full hybrid crop pyramid at its defaults, every crop embedded by the CLIP "
        "stand-in, blended across scales, interpolated to the target maps, distilled). The stand-in, a "
        f"1M-parameter CNN, was {trained}. Both scenes are queried with MiniLM and scored on the held-out "
        "views as served. The stand-in's crop accuracy on each scene's own held-out views (crops at the "
        "pyramid's scales, top-1 among the scene's names) bounds what its targets can carry.",
        "",
        "| seed | targets | 2D loc. | 3D loc. | mIoU | present found | absent rejected | crop acc. | s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        for kind in ("labels", "clip"):
            q = r[kind]
            found, rejected = _presence(q)
            acc = f"{r['crop_accuracy']:.3f}" if kind == "clip" else ""
            loc = f"{q['localisation_2d']:.3f} | {q['localisation_3d']:.3f} | {q['miou']:.3f}"
            secs = r["build_seconds"][kind]
            lines.append(f"| {r['seed']} | {kind} | {loc} | {found} | {rejected} | {acc} | {secs:.0f} |")
    keys = ("localisation_2d", "localisation_3d", "miou")
    for kind in ("labels", "clip"):
        m = [float(np.mean([r[kind][k] for r in rows])) for k in keys]
        lines.append(f"| mean | {kind} | {m[0]:.3f} | {m[1]:.3f} | {m[2]:.3f} | | | | |")
    mi = {k: float(np.mean([r[k]["miou"] for r in rows])) for k in ("labels", "clip")}
    acc = float(np.mean([r["crop_accuracy"] for r in rows]))
    hyb = {r["max_stride"]: r["object_pixels"] for r in knob if r["scales"] == "hybrid"}
    lines += [
        "",
        f"Reading: the CLIP path's mIoU ({mi['clip']:.3f}) stays below the label path's ({mi['labels']:.3f}) "
        f"by more than the stand-in's crop accuracy ({acc:.3f}) explains. The table below finds where: "
        f"before distillation its hybrid targets put {hyb.get(0.05, float('nan')):.0%} of object pixels "
        "nearest their own name at the default stride cap, because the equal mean of seven scales weighs "
        "the coarse crops (a quarter to half of the image, around objects a tenth of it) as much as the fine "
        "ones: that is the method's hybrid feature, not a misplaced crop. The paper's lattice put only "
        f"{hyb.get(None, float('nan')):.0%} there; the stride cap is the pipeline's fix (on one 128x96 "
        "scene before it (surface geometry, 300 field steps), the CLIP path localised 12% of held-out "
        "queries in 2D against the label path's 65%). A denser cap buys more for more crops (the 0.025 row).",
        "",
        "## Where the targets lose meaning: the crop lattice",
        "",
        f"Before any distillation, the CLIP targets of seed {knob_seed}'s first 4 views, per crop-stride "
        "cap (`--crop-stride`): the share of pixels, and of object pixels (neither floor nor background), "
        "whose target is nearest their own label's name; the hybrid (what the build distils) and each "
        "scale alone. Every crop is embedded by the stand-in; only the crops' spacing changes. With the "
        "paper's lattice (half the crop edge) a coarse scale's map interpolates crops centred far from "
        "the pixel, so on small objects it names the neighbours, and the equal mean of 7 scales follows "
        "the coarse majority. The build's default caps every scale's stride at 0.05 of the shorter side "
        "(the finest crop's edge); the scenes above were built with it.",
        "",
        *knob_table(knob),
        "",
        "What this shows and what it cannot: the stand-in gives the CLIP path meaning (a crop's embedding "
        "lands near its centre label's name), so a misaligned crop, a wrong scale blend or a shifted "
        "interpolation would move each phrase's relevancy off its object and cost localisation here. It "
        "cannot show how CLIP's own embeddings of real photos behave: its open vocabulary, its narrow "
        "similarity range (best cosines 0.2-0.35), its response to context around an object. Those need "
        "pretrained weights.",
        "",
    ]
    return "\n".join(lines)


STRIDE_CAPS = (None, 0.1, 0.05, 0.025)
"""The crop-stride caps the knob table compares (None: the paper's lattice, half the crop edge)."""


def target_map_accuracy(
    data: Path, standin: Path, views: int = 4, caps: tuple[float | None, ...] = STRIDE_CAPS
) -> list[dict]:
    """How well the CLIP targets themselves place each name, before any distillation, on the first
    ``views`` views of a generated scene: for each crop-stride cap (``caps``), each pyramid scale alone
    and the hybrid of all, the share of pixels (all, and object pixels: label >= 2) whose target is
    nearest their own label's name, and the crops embedded per view. Each scale's crops are embedded
    once per cap; the hybrid is their equal mean, renormalised, as fmgs.features.pyramid.hybrid_map."""
    import torch
    from PIL import Image

    from fmgs.features.pyramid import PyramidConfig, crop_grid, scale_map
    from fmgs.features.standin import load_standin
    from fmgs.features.text import MiniLMTextEncoder
    from fmgs.vecmath import safe_normalize

    names = json.loads((data / "scene.json").read_text())["label_names"]
    enc = load_standin(f"standin:{standin}")
    with torch.inference_mode():
        table = MiniLMTextEncoder().encode_text(names)
    rows = []
    for cap in caps:
        cfg = PyramidConfig(crop_px=enc.image_size, max_stride=cap)
        keys = ["hybrid", *map(str, cfg.scales)]
        hits = {k: np.zeros(4) for k in keys}
        crops = 0
        for p in sorted((data / "images").iterdir())[:views]:
            img = torch.from_numpy(np.asarray(Image.open(p).convert("RGB"), np.float32) / 255.0)
            lab = torch.from_numpy(np.asarray(Image.open(data / "labels" / p.name)).astype(np.int64))
            H, W = lab.shape
            maps = []
            for s in cfg.scales:
                g = crop_grid(H, W, s, cfg.overlap, cap)
                crops += g.boxes.shape[0] * g.boxes.shape[1]
                with torch.inference_mode():
                    maps.append(scale_map(enc, img.permute(2, 0, 1), g, cfg, (H, W)))
            # The hybrid exactly as hybrid_map blends it: the mean of the scales' maps, renormalised.
            for k, m in zip(keys, [safe_normalize(sum(maps) / len(maps)), *maps], strict=True):
                ok = (m @ table.T).argmax(-1) == lab
                hits[k] += [float(ok.sum()), ok.numel(), float(ok[lab >= 2].sum()), float((lab >= 2).sum())]
        for k in keys:
            h = hits[k]
            acc = {"pixels": h[0] / h[1], "object_pixels": h[2] / max(h[3], 1.0)}
            rows.append({"max_stride": cap, "scales": k, **acc, "crops_per_view": crops / views})
    return rows


def knob_table(rows: list[dict]) -> list[str]:
    """Markdown: per stride cap, crops per view and the hybrid's accuracy, then each scale alone."""
    scales = [r["scales"] for r in rows if r["max_stride"] is None and r["scales"] != "hybrid"]
    head = "| crop stride cap | crops / view | hybrid: pixels | hybrid: object pixels | "
    head += " | ".join(f"{s} alone" for s in scales) + " |"
    lines = [head, "|" + "---|" * (4 + len(scales))]
    for cap in STRIDE_CAPS:
        rs = {r["scales"]: r for r in rows if r["max_stride"] == cap}
        h = rs["hybrid"]
        name = "none (paper: crop edge / 2)" if cap is None else f"{cap} of the shorter side"
        cells = " | ".join(f"{rs[s]['object_pixels']:.3f}" for s in scales)
        lines.append(
            f"| {name} | {h['crops_per_view']:.0f} | {h['pixels']:.3f} | {h['object_pixels']:.3f} | {cells} |"
        )
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--seeds", default="104,105,106")
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--size", default="128x96")
    ap.add_argument("--gs-steps", type=int, default=3000)
    ap.add_argument("--field-steps", type=int, default=1500, help="field steps of both builds (default 1500)")
    ap.add_argument(
        "--grad-threshold", type=float, default=0.001, help="3DGS densification threshold (default 0.001)"
    )
    ap.add_argument("--standin", default=str(STANDIN), help="the stand-in's folder (standin.json, weights)")
    ap.add_argument("--quick", action="store_true", help="smoke run: one 64x48 scene, short stages")
    ap.add_argument("--from-json", metavar="JSON", help="only write the report again from a clip_path.json")
    ap.add_argument("--report", action="store_true", help="also write benchmarks/results/CLIP_PATH.md")
    ap.add_argument(
        "--target-maps",
        metavar="DATA",
        help="only print, for a generated scene DATA, how well the CLIP targets alone place each name, per "
        "pyramid scale and for their hybrid (pixel accuracy, all and object pixels)",
    )
    a = ap.parse_args()
    if a.from_json:
        d = json.loads(Path(a.from_json).read_text())
        standin_cfg = json.loads((Path(a.standin) / "standin.json").read_text())
        text = report(
            d["rows"], d["machine"], d["command"], standin_cfg, d["target_maps"], d["rows"][0]["seed"]
        )
        save_report(text, Path(a.out), "CLIP_PATH.md", a.report)
        print(text)
        return 0
    if a.target_maps:
        print("\n".join(knob_table(target_map_accuracy(Path(a.target_maps), Path(a.standin)))))
        return 0
    if a.quick:
        a.seeds, a.views, a.size, a.gs_steps, a.field_steps = "7", 24, "64x48", 300, 150
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    standin = Path(a.standin).resolve()
    standin_cfg = json.loads((standin / "standin.json").read_text())
    rows = []
    for seed in (int(s) for s in a.seeds.split(",")):
        data = build_scene(out, seed, a.views, a.size, a.gs_steps, a.field_steps, a.grad_threshold)
        clip_build(out, seed, data, standin, a.field_steps)
        rows.append(score(out, seed, data, standin))
        (out / "clip_path.json").write_text(json.dumps({"rows": rows}, indent=1, default=float))
    first = out / f"scene-{rows[0]['seed']}"
    knob = target_map_accuracy(first, standin)
    info = {**machine(), "date": time.strftime("%Y-%m-%d")}
    cmd = "python -m benchmarks.clip_path " + " ".join(sys.argv[1:])
    text = report(rows, info, cmd, standin_cfg, knob, rows[0]["seed"])
    (out / "clip_path.json").write_text(
        json.dumps(
            {"rows": rows, "target_maps": knob, "machine": info, "command": cmd}, indent=1, default=float
        )
    )
    save_report(text, out, "CLIP_PATH.md", a.report)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
