"""Per-class calibration of segmentation, measured against the served argmax.

Segmentation (fmgs.query.segment) labels a pixel with the class whose rendered dot is largest. A field
distilled from crop targets gives a small object a lower peak dot with its own name than the floor gets
with "floor" (its targets mix the object with what surrounds it), so at the object's boundary the
floor's larger scale wins. Relevancy maps are normalised per query for this reason (LERF, LangSplat):
here each class's dots are divided by its scene max, the dot of its best-matching embedded Gaussian.
That presumes every class is in the scene (the 3D-OVS protocol); an absent name's best match is
stretched to 1 as well. So each package is scored with the scene's names alone and with absent names
added (benchmarks.unseen.world_presence_queries' absent objects and colour swaps), each way three
rules: ``raw`` (served), ``scene max``, and ``scene max if present`` (only classes the served presence
rule finds in the scene are divided). A pixel an absent name takes counts against its true class.

    python -m benchmarks.segment_calibration --out OUT [--seeds 201,202,203] [--variants dominant] [--report]

OUT is a benchmarks.clip_path output folder (its scenes and packages); the label build of each seed is
scored with the variants. Writes segment_calibration.json and SEGMENT_CALIBRATION.md into OUT (with
--report, into benchmarks/results/ too).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

RULES = ("raw", "scene max", "scene max if present")
ABSENT_KINDS = ("absent object", "colour swap")


def divisors(engine, classes: torch.Tensor, found: torch.Tensor) -> dict[str, torch.Tensor]:
    """Each rule's [n] positive divisor of the classes' dots, for unit class embeddings [n,D] and the
    presence rule's verdicts [n] bool: 1 (raw), the class's largest dot over every embedded Gaussian (the
    channels segmentation renders), that only where the class is found present. A scene max <= 0 (no
    Gaussian points the class's way) leaves the class raw: dividing would flip its dots' order."""
    top = engine.channels(classes, None).amax(0)
    best = torch.where(top > 0, top, torch.ones_like(top))
    one = torch.ones_like(top)
    return {"raw": one, "scene max": best, "scene max if present": torch.where(found, best, one)}


def calibrated_labels(dots: torch.Tensor, alpha: torch.Tensor, divisor: torch.Tensor) -> np.ndarray:
    """[H,W] int64 argmax of rendered class dots [H,W,n] divided by divisor [n], -1 where segmentation
    leaves the pixel unlabelled (fmgs.query.segment.pixel_labels)."""
    from fmgs.query.segment import pixel_labels

    return pixel_labels(dots / divisor, alpha).numpy().astype(np.int64)


def presence_found(engine, encoder, texts: list[str], vecs: torch.Tensor) -> torch.Tensor:
    """[n] bool: the served presence rule's verdict for each text, as benchmarks.unseen scores it."""
    from fmgs.query.presence import negative_names, probes

    negs = encoder.encode_text(negative_names(engine.manifest.label_names))
    pr = probes(texts, vecs, encoder.encode_text)
    answers = engine.text_query_many(vecs, 10, negatives=negs, probes=pr)
    return torch.tensor([a.presence.found for a in answers])


def package_scores(engine, ds, encoder, views: list[int], names: list[str], absent: list[str]) -> dict:
    """mIoU over the scene's classes (label 0, the background, left out) per class set and rule, and how
    many of each set's texts presence finds."""
    from PIL import Image

    from fmgs.query.segment import class_dots
    from fmgs.train.evaluate_field import add_overlaps, class_ious

    out: dict = {}
    for which, texts in (("scene names", names[1:]), ("with absent names", names[1:] + absent)):
        vecs = encoder.encode_text(texts).float()
        found = presence_found(engine, encoder, texts, vecs)
        rules = divisors(engine, engine.unit(vecs, "class embeddings"), found)
        acc = {r: (np.zeros(len(names)), np.zeros(len(names))) for r in rules}
        for i in views:
            fr = ds.frames[i]
            dots, alpha = class_dots(engine, vecs, fr.camera)
            gt = np.asarray(Image.open(ds.root / "labels" / Path(fr.name).name)).astype(np.int64)
            for r, d in rules.items():
                lab = calibrated_labels(dots, alpha, d)
                lab[lab >= len(names) - 1] = -2  # an absent name: no label's pixel, a miss for the true one
                add_overlaps(lab, gt, *acc[r])
        out[which] = {
            "miou": {r: float(np.mean(list(class_ious(*acc[r], names).values()))) for r in rules},
            "found": int(found.sum()),
            "texts": len(texts),
            "present_found": int(found[: len(names) - 1].sum()),
        }
    return out


def run_seed(out: Path, seed: int, variants: list[str]) -> dict:
    from benchmarks.clip_variants import variant_name
    from benchmarks.unseen import world_presence_queries
    from fmgs.data import HOLDOUT_EVERY
    from fmgs.data.dataset import load_dataset
    from fmgs.features.text import MiniLMTextEncoder
    from fmgs.query.engine import SceneEngine

    data = out / f"scene-{seed}"
    ds = load_dataset(data)
    _, test = ds.split(HOLDOUT_EVERY)
    names = json.loads((data / "scene.json").read_text())["label_names"]
    absent = [t for k, t in world_presence_queries(names) if k in ABSENT_KINDS]
    enc = MiniLMTextEncoder()
    row: dict = {"seed": seed, "absent": absent, "kinds": {}}
    for kind in ["labels", *variants]:
        pkg = out / "models" / (f"s{seed}" if kind == "labels" else variant_name(seed, kind))
        if (pkg / "manifest.json").is_file():
            row["kinds"][kind] = package_scores(SceneEngine.open(pkg), ds, enc, test, names, absent)
    return row


def report(d: dict) -> str:
    from benchmarks.common import machine_words

    rows = d["rows"]
    kinds = [k for k in rows[0]["kinds"] if all(k in r["kinds"] for r in rows)]

    def mean(kind: str, which: str, rule: str) -> float:
        return float(np.mean([r["kinds"][kind][which]["miou"][rule] for r in rows]))

    n_absent = sorted({len(r["absent"]) for r in rows})
    lines = [
        "# Per-class calibration of segmentation",
        "",
        f"Measured {d['machine']['date']} on {machine_words(d['machine'])}, one run of `{d['command']}`.",
        "",
        f"Scenes: CLIP_PATH.md's unseen seeds {', '.join(str(r['seed']) for r in rows)}, the packages of "
        "one clip_path output folder (each seed's label build and the CLIP variants on its 3DGS), queried "
        "with MiniLM on the held-out views. Segmentation's pixel labels (fmgs.query.segment: the argmax of "
        "the rendered class dots) under three rules: **raw**, as served; **scene max**, each class's dots "
        "divided by its best embedded Gaussian's dot (relevancy normalised per query, as LERF and "
        "LangSplat do); **scene max if present**, only the classes the served presence rule finds divided. "
        "Each with the scene's names alone (floor and objects: the 3D-OVS protocol, every class present) "
        f"and with {'/'.join(map(str, n_absent))} absent names added (each absent shape in a colour, each "
        "object in the next colour: what a user's vocabulary may hold); a pixel an absent name takes "
        "counts against its true class. mIoU over the floor and the objects.",
        "",
        "## Means over the scenes",
        "",
        "| targets | names | " + " | ".join(RULES) + " |",
        "|---|---|" + "---:|" * len(RULES),
    ]
    for k in kinds:
        for which in ("scene names", "with absent names"):
            cells = " | ".join(f"{mean(k, which, r):.3f}" for r in RULES)
            lines.append(f"| {k} | {which} | {cells} |")
    head = "| seed | targets | names | " + " | ".join(RULES) + " | texts found present |"
    lines += ["", "## Per scene", "", head, "|---|---|---|" + "---:|" * (len(RULES) + 1)]
    for r in rows:
        for k in kinds:
            for which, s in r["kinds"][k].items():
                cells = " | ".join(f"{s['miou'][x]:.3f}" for x in RULES)
                lines.append(f"| {r['seed']} | {k} | {which} | {cells} | {s['found']}/{s['texts']} |")
    lines += ["", *[f"- {n}" for n in d.get("notes", [])]]
    return "\n".join(lines).rstrip() + "\n"


def main() -> int:
    from benchmarks.common import command_line, machine

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="benchmarks.clip_path's output folder (the builds)")
    ap.add_argument("--seeds", default="201,202,203")
    ap.add_argument("--variants", default="dominant", help="CLIP variants scored beside the label build")
    ap.add_argument("--note", action="append", default=[], help="a line for the report's notes")
    ap.add_argument(
        "--report", action="store_true", help="also write benchmarks/results/SEGMENT_CALIBRATION.md"
    )
    ap.add_argument("--from-json", metavar="JSON", help="only write the report again from its JSON")
    a = ap.parse_args()
    out = Path(a.out)
    if a.from_json:
        d = json.loads(Path(a.from_json).read_text())
        d["notes"] = [*d.get("notes", []), *a.note]
        return _write(d, out, a.report)
    variants = [v for v in a.variants.split(",") if v]
    rows = [run_seed(out, int(s), variants) for s in a.seeds.split(",")]
    d = {"rows": rows, "machine": {**machine(), "date": time.strftime("%Y-%m-%d")}, "notes": a.note,
         "command": command_line("benchmarks.segment_calibration")}  # fmt: skip
    return _write(d, out, a.report)


def _write(d: dict, out: Path, publish: bool) -> int:
    from benchmarks.common import save_result

    text = report(d)
    save_result(d, out, "SEGMENT_CALIBRATION", text, publish)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
