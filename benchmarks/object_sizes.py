"""The CLIP path by object size: where its gap to the label path lies.

CLIP_PATH.md scores each build's mIoU over all of a scene's objects. This report splits the same per-object
IoUs (read from a clip_path report's JSON: served segmentation on the held-out views) by each object's
size, its mean share of the held-out views' pixels, in three bands fixed before looking: under 0.25% of
the image, 0.25% to 1%, and 1% or more (on 128x96 views: under 31 pixels, 31 to 122, 123 or more).

It also measures the targets alone, per object and by the same bands (on the first views, as
CLIP_PATH.md's target-map table): the default blend (``dominant``) of the CLIP stand-in's crops and its
finest scale alone, against the same crops named without error (benchmarks.clip_oracle), each with the
default pyramid and with one finer scale (half the finest crop's edge), the stand-in's crops cut from the
views as rendered and from the same views at twice the width and height
(benchmarks.clip_variants.photos_scene; the maps at the scene's size). That tells the crop pyramid's
geometry from the stand-in's naming as causes of the loss on small objects.

    python -m benchmarks.object_sizes --out OUT [--scores benchmarks/results/CLIP_PATH.json]
        [--seeds 201,202,203] [--target-views 6] [--report]

OUT holds (or receives: generated again from their seeds, checked against the scores' objects) the scenes
as benchmarks.clip_path lays them out. Writes object_sizes.json and OBJECT_SIZES.md into OUT (with
--report, into benchmarks/results/ too).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

BANDS = (0.0025, 0.01)
"""Band edges as shares of the image's pixels: [0, 0.25%), [0.25%, 1%), [1%, ...)."""
BAND_NAMES = ("under 0.25%", "0.25-1%", "1% or more")
TARGETS = ("stand-in", "no naming error")
PYRAMIDS = ("default pyramid", "finer scale")
PHOTOS = (1, 2)


def band(share: float) -> int:
    """The band (index into BAND_NAMES) of an object covering ``share`` of the image's pixels."""
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"an object's share of the image must be in [0, 1], got {share}")
    return int(np.searchsorted(BANDS, share, side="right"))


def candidate(target: str, pyramid: str, photos: int, blend: str) -> str:
    """A row name of the targets' table."""
    return f"{target}, {pyramid}" + (f", photos x{photos}" if photos > 1 else "") + f": {blend}"


def blends(maps: list[torch.Tensor], edges: list[float], dense: torch.Tensor) -> dict[str, torch.Tensor]:
    """{"dominant": the default blend, "finest alone": the finest scale's map} of per-scale maps [h,w,D]
    with their crop edges (map pixels) and the DINO map [h,w,Dd], each [h,w,D] unit."""
    from fmgs.features.scale_blend import blend_scales, scale_weights

    finest = int(np.argmin(edges))
    return {
        "dominant": blend_scales(maps, scale_weights("dominant", dense, edges)),
        "finest alone": torch.nn.functional.normalize(maps[finest], dim=-1),
    }


def label_areas(labels: list[np.ndarray], classes: int) -> np.ndarray:
    """[classes] each label id's mean pixel count over the label maps [H,W] (ids 0..classes-1)."""
    tot = np.zeros(classes)
    for lab in labels:
        tot += np.bincount(lab.ravel(), minlength=classes)[:classes]
    return tot / max(len(labels), 1)


def band_means(objects: list[dict], key: str, kind: str) -> list[tuple[int, float]]:
    """Per band: (objects scored, mean IoU) of ``objects[i][key][kind]`` (objects without it left out)."""
    out = []
    for b in range(len(BAND_NAMES)):
        v = [o[key][kind] for o in objects if band(o[f"share_{key}"]) == b and o[key].get(kind) is not None]
        out.append((len(v), float(np.mean(v)) if v else float("nan")))
    return out


def served_ious(row: dict) -> dict[str, dict[str, float]]:
    """{targets: {object: IoU}} of one clip_path row: its variants, and the builds made again for the later
    variants under "(made again)"."""
    kinds = {k: v["class_iou"] for k, v in row["kinds"].items()}
    if row.get("refit_labels"):
        kinds["labels (made again)"] = row["refit_labels"]["class_iou"]
    for k, v in row.get("refit_variants", {}).items():
        kinds[f"{k} (made again)"] = v["class_iou"]
    return kinds


def target_ious(data: Path, photos: dict[int, Path], views: int) -> tuple[dict[str, list[float]], np.ndarray]:
    """({candidate: [C] IoU per label id}, [C] mean pixels per label) of the default blend's target maps
    on the first ``views`` views of ``data`` (see the module docstring); ``photos``: {factor: the scene
    rendered at that factor}."""
    from PIL import Image

    from benchmarks.clip_oracle import oracle_scale_maps
    from benchmarks.clip_targets import novel_labels, standin_scene, tally
    from fmgs.features.pyramid import PyramidConfig, scale_maps
    from fmgs.features.standin import WALL, extended_labels

    names, enc, dino, table, points = standin_scene(data)
    base = PyramidConfig(crop_px=enc.image_size)
    pyramids = {PYRAMIDS[0]: base, PYRAMIDS[1]: replace(base, scales=(min(base.scales) / 2, *base.scales))}
    C = len(names)
    novel = novel_labels(data)
    acc: dict[str, np.ndarray] = {}

    labels = []
    for p in sorted((data / "images").iterdir())[:views]:
        lab = torch.from_numpy(np.asarray(Image.open(data / "labels" / p.name)).astype(np.int64))
        labels.append(lab.numpy())
        H, W = lab.shape
        with torch.inference_mode():
            img = torch.from_numpy(np.asarray(Image.open(p).convert("RGB"), np.float32) / 255.0)
            dense = dino.dense(img, (H, W))
            ext = extended_labels(data, p.stem, names)
            for pname, cfg in pyramids.items():
                for f in PHOTOS:
                    src = photos[f] / "images" / p.name if f > 1 else p
                    im = torch.from_numpy(np.asarray(Image.open(src).convert("RGB"), np.float32) / 255.0)
                    sm = scale_maps(enc, im, cfg, (H, W))
                    scores = {candidate(TARGETS[0], pname, f, b): t @ table.T
                              for b, t in blends(sm.maps, sm.edges, dense).items()}  # fmt: skip
                    tally(acc, scores, lab, novel, C)
                om, oe = oracle_scale_maps(ext, [*names, WALL], points, cfg, (H, W))
                named = blends(om, oe, dense)
                scores = {candidate(TARGETS[1], pname, 1, b): t @ table.T for b, t in named.items()}
                tally(acc, scores, lab, novel, C)
    # tally's counts: six pixel counts, then each class's (label ids 1..C-1) intersection and union
    ious = {k: [0.0, *(v[6 : 5 + C] / np.maximum(v[5 + C :], 1.0)).tolist()] for k, v in acc.items()}
    return ious, label_areas(labels, C)


def run_seed(out: Path, row: dict, views: int, size: str, target_views: int) -> dict:
    """One scene's objects: their shares of the held-out and target views, served and target IoUs."""
    from PIL import Image

    from benchmarks.clip_path import synth_flags
    from benchmarks.clip_variants import photos_scene
    from benchmarks.unseen import synth_scene
    from fmgs.data import HOLDOUT_EVERY
    from fmgs.data.dataset import load_dataset

    seed = row["seed"]
    data = synth_scene(out / f"scene-{seed}", seed, views, size, synth_flags(seed), preset="world")
    names = json.loads((data / "scene.json").read_text())["label_names"]
    if names[2:] != row["objects"]:
        raise ValueError(f"{data} holds {names[2:]}, the scores were measured on {row['objects']}")
    ds = load_dataset(data)
    _, test = ds.split(HOLDOUT_EVERY)
    held = [np.asarray(Image.open(ds.root / "labels" / Path(ds.frames[i].name).name)) for i in test]
    pixels = held[0].size
    served_area = label_areas(held, len(names))
    photos = {2: photos_scene(data, out / f"{data.name}-x2", 2)}
    targets, target_area = target_ious(data, photos, target_views)
    served = served_ious(row)
    objects = []
    for c, name in enumerate(names):
        if c < 2:
            continue  # background and floor
        objects.append({
            "name": name,
            "share_served": float(served_area[c] / pixels),
            "share_targets": float(target_area[c] / pixels),
            "served": {k: v.get(name) for k, v in served.items()},
            "targets": {k: (v[c] if target_area[c] > 0 else None) for k, v in targets.items()},
        })  # fmt: skip
    return {"seed": seed, "objects": objects, "held_out_views": len(test), "target_views": target_views}


def report(d: dict) -> str:
    from benchmarks.common import machine_words

    objs = [o for r in d["rows"] for o in r["objects"]]
    m = d["machine"]
    head = "| targets | " + " | ".join(f"{b} (objects) | {b} IoU" for b in BAND_NAMES) + " |"
    rule = "|---|" + "---:|---:|" * len(BAND_NAMES)

    def rows(key: str, kinds: list[str]) -> list[str]:
        lines = [head, rule]
        for k in kinds:
            cells = [f"{n} | {v:.3f}" if n else "0 | -" for n, v in band_means(objs, key, k)]
            lines.append(f"| {k} | " + " | ".join(cells) + " |")
        return lines

    served = list(dict.fromkeys(k for o in objs for k in o["served"]))
    targets = list(dict.fromkeys(k for o in objs for k in o["targets"]))
    lines = [
        "# The CLIP path by object size",
        "",
        f"Measured {m['date']} on {machine_words(m)}, one run of `{d['command']}`, on the scores of "
        f"`{d['scores']}` (seeds {', '.join(str(r['seed']) for r in d['rows'])}).",
        "",
        __doc__.split("\n\n")[1].replace("\n", " "),
        "",
        "## Served segmentation on the held-out views, mean object IoU by size",
        "",
        "Each object's IoU as the scores hold it (mIoU there also counts the floor); its size is its mean "
        "share of the held-out views' pixels (views where it is hidden count as 0).",
        "",
        *rows("served", served),
        "",
        "## The targets alone, mean object IoU by size",
        "",
        __doc__.split("\n\n")[2].replace("\n", " ")
        + f" Sizes here are shares of the first {d['rows'][0]['target_views']} views' pixels; objects "
        "not seen in them are left out.",
        "",
        *rows("targets", targets),
        "",
        "## Objects",
        "",
        "| seed | object | share of held-out views | labels | default (dominant) |",
        "|---|---|---:|---:|---:|",
    ]
    for r in d["rows"]:
        for o in sorted(r["objects"], key=lambda o: o["share_served"]):
            lab, dom = o["served"].get("labels"), o["served"].get("dominant")
            lines.append(f"| {r['seed']} | {o['name']} | {o['share_served']:.2%} | {lab:.3f} | {dom:.3f} |")
    if d.get("notes"):
        lines += ["", "## Notes", "", *[f"- {n}" for n in d["notes"]]]
    return "\n".join(lines) + "\n"


def main() -> int:
    from benchmarks.common import RESULTS, ROOT, command_line, machine

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="folder of the scenes (generated again when absent)")
    ap.add_argument("--scores", default=str(RESULTS / "CLIP_PATH.json"), help="a clip_path report's JSON")
    ap.add_argument("--seeds", default="201,202,203")
    ap.add_argument("--views", type=int, default=48, help="the scenes' views (as clip_path made them)")
    ap.add_argument("--size", default="128x96", help="the scenes' size (as clip_path made them)")
    ap.add_argument("--target-views", type=int, default=6, help="views per scene of the targets' table")
    ap.add_argument("--note", action="append", default=[], help="a line for the report's notes")
    ap.add_argument("--report", action="store_true", help="also write benchmarks/results/OBJECT_SIZES.md")
    ap.add_argument("--from-json", metavar="JSON", help="only write the report again from its JSON")
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    if a.from_json:
        d = json.loads(Path(a.from_json).read_text())
        d["notes"] = [*d.get("notes", []), *a.note]
        return _write(d, out, a.report)
    scores = json.loads(Path(a.scores).read_text())
    by_seed = {r["seed"]: r for r in scores["rows"]}
    seeds = [int(s) for s in a.seeds.split(",") if s]
    missing = [s for s in seeds if s not in by_seed]
    if missing:
        raise SystemExit(f"{a.scores} holds no scores of seeds {missing} (it holds {sorted(by_seed)})")
    rows = [run_seed(out, by_seed[s], a.views, a.size, a.target_views) for s in seeds]
    scores_name = Path(a.scores).resolve()
    shown = scores_name.relative_to(ROOT) if scores_name.is_relative_to(RESULTS) else Path(a.scores)
    d = {"rows": rows, "scores": str(shown), "machine": {**machine(), "date": time.strftime("%Y-%m-%d")},
         "notes": a.note, "command": command_line("benchmarks.object_sizes")}  # fmt: skip
    return _write(d, out, a.report)


def _write(d: dict, out: Path, publish: bool) -> int:
    from benchmarks.common import save_result

    text = report(d)
    save_result(d, out, "OBJECT_SIZES", text, publish)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
