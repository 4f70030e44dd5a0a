"""Where distillation gains or loses against its targets: per class, the targets, the field on the views it
was trained on, and the field on held-out views.

    python -m benchmarks.distill_gap DATA NAME=PACKAGE:FEATURES[:FIELD] [...] [--out DIR] [--report]

For a generated scene (fmgs synth, with labels) and builds of it (each a scene package and the feature cache
it was distilled from, e.g. models/NAME and models/.work/NAME/features, and the folder of its
field_train.json when it is not models/.work/NAME/field), per class: the IoU of the target
maps themselves (argmax over the scene's names but the background, every training view, pixels with a
label), the IoU of the package's served segmentation on the training views and on the held-out views
(fmgs.train.evaluate_field), and what the held-out pixels of each object are taken for. Also the targets'
mean squares per element and what they make of the loss's weights: under ``balance`` "paper", equal
relative errors cost the DINO term ((1 - lam) * DINO mean square) against the language term's
(lam * language mean square / 2: the Huber loss's quadratic part), the ratio the report gives.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import RESULTS, machine, machine_words, save_report

REPORT = "DISTILL_GAP.md"


def target_ious(data: Path, cache, names: list[str], table: torch.Tensor, frames: list[str]) -> np.ndarray:
    """[K] IoU of the cache's language targets' argmax over names[1:] against the label maps (0: none)."""
    from PIL import Image

    K = len(names)
    inter, union = np.zeros(K), np.zeros(K)
    for name in frames:
        maps = cache.load(name)
        h, w = maps.clip.shape[:2]
        lab = torch.from_numpy(np.asarray(Image.open(data / "labels" / Path(name).name)).astype(np.int64))
        lab = torch.nn.functional.interpolate(lab[None, None].float(), size=(h, w), mode="nearest")[0, 0]
        lab = lab.long().numpy()
        pred = (torch.nn.functional.normalize(maps.clip.float(), dim=-1) @ table.T).argmax(-1).numpy() + 1
        valid = lab > 0
        for c in range(1, K):
            p, t = (pred == c) & valid, (lab == c) & valid
            inter[c] += np.sum(p & t)
            union[c] += np.sum(p | t)
    return inter / np.maximum(union, 1)


def mean_squares(cache, frames: list[str]) -> dict[str, float]:
    """Mean square per element of each target over the frames (masked pixels only, where masked)."""
    sums: dict[str, float] = {}
    counts: dict[str, int] = {}
    for name in frames:
        maps = cache.load(name)
        for key in ("clip", "dino"):
            t = getattr(maps, key)
            if t is None:
                continue
            t = t.reshape(-1, t.shape[-1])
            if maps.mask is not None:
                t = t[maps.mask.reshape(-1)]
            sums[key] = sums.get(key, 0.0) + float(t.double().square().sum())
            counts[key] = counts.get(key, 0) + t.numel()
    return {k: sums[k] / max(counts[k], 1) for k in sums}


def confusion(engine, ds, emb: torch.Tensor, views: list[int], names: list[str]) -> np.ndarray:
    """[K, K+1] pixel counts over ``views``: label map class (rows) against the served segmentation's
    class (columns; the last: unlabelled, where the embedded Gaussians barely cover the pixel)."""
    from PIL import Image

    from fmgs.query.segment import segment

    K = len(names)
    conf = np.zeros((K, K + 1), np.int64)
    for i in views:
        lab = segment(engine, emb[1:], ds.frames[i].camera, per_gaussian=False).pixel_labels.numpy()
        pred = np.where(lab >= 0, lab + 1, K)
        gt = np.asarray(Image.open(ds.root / "labels" / Path(ds.frames[i].name).name)).astype(np.int64)
        np.add.at(conf, (gt.ravel(), pred.ravel()), 1)
    return conf


def class_ious(conf: np.ndarray, names: list[str]) -> dict[str, float]:
    """IoU per class present in a ``confusion`` matrix, scored as fmgs.train.evaluate_field scores it:
    labelled pixels only (row 0, no geometry, left out), an unlabelled pixel a miss."""
    out = {}
    for c in range(1, len(names)):
        union = conf[c].sum() + conf[1:, c].sum() - conf[c, c]
        if union > 0:
            out[names[c]] = float(conf[c, c] / union)
    return out


def confusions(conf: np.ndarray, names: list[str]) -> dict[str, dict[str, float]]:
    """Object name -> {what its pixels are labelled: share} (the top three; "none": unlabelled)."""
    K = len(names)
    out = {}
    for c in range(1, K):
        row = conf[c] / max(conf[c].sum(), 1)
        top = np.argsort(-row)[:3]
        out[names[c]] = {(names[j] if j < K else "none"): round(float(row[j]), 3) for j in top if row[j] > 0}
    return out


def measure(data: Path, builds: dict[str, tuple[Path, Path, Path]]) -> dict:
    from fmgs.data import HOLDOUT_EVERY
    from fmgs.data.dataset import load_dataset
    from fmgs.features.cache import FeatureCache
    from fmgs.features.text import MiniLMTextEncoder
    from fmgs.query.engine import SceneEngine
    from fmgs.train.evaluate_field import evaluate_field

    ds = load_dataset(data)
    names = json.loads((data / "scene.json").read_text())["label_names"]
    enc = MiniLMTextEncoder()
    emb = enc.encode_text(names).float()
    train, test = ds.split(HOLDOUT_EVERY)
    frames = [ds.frames[i].name for i in train]
    out = {"scene": str(data), "names": names, "builds": {}}
    for label, (package, features, field) in builds.items():
        cache = FeatureCache.open(features)
        engine = SceneEngine.open(package)
        field_json = field / "field_train.json"
        cfg = json.loads(field_json.read_text())["config"] if field_json.is_file() else {}
        te = evaluate_field(engine, ds, enc, test, data / "scene.json")  # localisation; IoU as below
        held = confusion(engine, ds, emb, test, names)
        ious = target_ious(data, cache, names, emb[1:], frames)
        out["builds"][label] = {
            "package": str(package),
            "features": str(features),
            "lam": cfg.get("lam"),
            "balance": cfg.get("balance", "paper"),
            "mean_squares": mean_squares(cache, frames),
            "targets": {names[c]: float(ious[c]) for c in range(1, len(names))},
            "train": class_ious(confusion(engine, ds, emb, train, names), names),
            "heldout": class_ious(held, names),
            "localisation_2d": te.localisation_2d,
            "localisation_3d": te.localisation_3d,
            "confusions": confusions(held, names),
        }
    return out


def dino_weight(b: dict) -> float | None:
    """DINO term : language term for equal relative errors (None without DINO targets or a known lam):
    under "paper" the targets' mean squares enter, under "scale" they are divided out."""
    ms, lam = b["mean_squares"], b["lam"]
    if "dino" not in ms or lam is None:
        return None
    if b["balance"] == "scale":
        return (1 - lam) / (lam / 2)
    return (1 - lam) * ms["dino"] / (lam * ms["clip"] / 2)


def report(d: dict, cmd: str) -> str:
    names = d["names"][1:]
    builds = d["builds"]
    lines = [
        "# Distillation against its targets, per class",
        "",
        f"Measured {d['machine']['date']} on {machine_words(d['machine'])}, one run of `{cmd}` (scene "
        f"`{d['scene']}`). Targets: the feature cache's language maps over every training view (argmax over "
        "the scene's names but the background, on labelled pixels); train and held-out: the package's "
        "served segmentation (fmgs.train.evaluate_field) on the training and the held-out views; 2D and 3D: "
        "localisation on the held-out views, as CLIP_PATH.md scores it.",
        "",
        "| build | targets mIoU | train mIoU | held-out mIoU | 2D loc. | 3D loc. |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for label, b in builds.items():
        m = [float(np.mean([b[k].get(n, 0.0) for n in names])) for k in ("targets", "train", "heldout")]
        lines.append(
            f"| {label} | {m[0]:.3f} | {m[1]:.3f} | {m[2]:.3f} | {b['localisation_2d']:.3f} | "
            f"{b['localisation_3d']:.3f} |"
        )
    lines += [
        "",
        "## Per class",
        "",
        "IoU per class, each cell targets / train / held-out; the last row is the mean.",
        "",
        "| class | " + " | ".join(builds) + " |",
        "|---|" + "---:|" * len(builds),
    ]
    for n in [*names, "mean"]:
        cells = []
        for b in builds.values():
            xs = [
                float(np.mean([b[k].get(m, 0.0) for m in names])) if n == "mean" else b[k].get(n, 0.0)
                for k in ("targets", "train", "heldout")
            ]
            cells.append(" / ".join(f"{x:.2f}" for x in xs))
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "## The loss's balance",
        "",
        "Mean square per element of each build's targets, and what equal relative errors cost the DINO term "
        'against the language term: under `balance` "paper" (the paper\'s weights on the targets as they '
        "come), (1 - lam) x DINO mean square over lam x language mean square / 2 (the Huber loss's quadratic "
        'part); under "scale" (each term divided by its targets\' mean square first), (1 - lam) over '
        "lam / 2. The hash grid, which both heads share, follows the larger.",
        "",
        "| build | lam | balance | language mean square | DINO mean square | DINO : language |",
        "|---|---:|---|---:|---:|---:|",
    ]
    for label, b in builds.items():
        ms = b["mean_squares"]
        w = dino_weight(b)
        lines.append(
            f"| {label} | {b['lam']} | {b['balance']} | {ms['clip']:.2e} | "
            f"{ms.get('dino', float('nan')):.3g} | {'' if w is None else f'{w:.0f}'} |"
        )
    lines += ["", "## What the held-out pixels of each object are taken for", ""]
    for label, b in builds.items():
        lines.append(f"- **{label}**:")
        for n, row in b["confusions"].items():
            if n == d["names"][1]:
                continue  # the floor
            lines.append(f"  - {n}: " + ", ".join(f"{k} {v:.2f}" for k, v in row.items()))
    if d.get("notes"):
        lines += ["", "## Notes", "", *(f"- {x}" for x in d["notes"])]
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path, nargs="?")
    ap.add_argument(
        "builds",
        nargs="*",
        help="NAME=PACKAGE:FEATURES[:FIELD] (FIELD: where its field_train.json is; FEATURES/../field)",
    )
    ap.add_argument("--out", type=Path, default=Path("distill_gap_out"))
    ap.add_argument("--report", action="store_true", help=f"also write benchmarks/results/{REPORT}")
    ap.add_argument("--note", action="append", default=[], help="a line for the report's notes (repeatable)")
    ap.add_argument("--from-json", type=Path, help="only write the report again from a DISTILL_GAP.json")
    a = ap.parse_args()
    if a.from_json:
        d = json.loads(a.from_json.read_text())
        d["notes"] = [*d.get("notes", []), *a.note]
        if a.report:
            (RESULTS / "DISTILL_GAP.json").write_text(json.dumps(d, indent=1))
        save_report(report(d, d["command"]), a.out, REPORT, a.report)
        return 0
    if a.data is None or not a.builds:
        ap.error("give DATA and at least one NAME=PACKAGE:FEATURES (or --from-json)")
    builds = {}
    for spec in a.builds:
        label, _, paths = spec.partition("=")
        package, _, rest = paths.partition(":")
        features, _, field = rest.partition(":")
        if not (label and package and features):
            ap.error(f"a build is NAME=PACKAGE:FEATURES[:FIELD], not {spec!r}")
        field_dir = Path(field) if field else Path(features).parent / "field"
        builds[label] = (Path(package), Path(features), field_dir)
    d = measure(a.data, builds)
    d["machine"] = machine()
    cmd = "python -m benchmarks.distill_gap " + " ".join([str(a.data), *a.builds])
    d["command"], d["notes"] = cmd, a.note
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "DISTILL_GAP.json").write_text(json.dumps(d, indent=1))
    if a.report:
        (RESULTS / "DISTILL_GAP.json").write_text(json.dumps(d, indent=1))
    save_report(report(d, cmd), a.out, REPORT, a.report)
    print(report(d, cmd))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
