"""LERF's query-time scale selection on the Gaussians, lifted: one embedding per crop scale per Gaussian, each
name scored by its best scale, side by side with the default blend lifted onto the same Gaussians.

    python -m benchmarks.lerf_lift --out OUT [--seeds 201,202,203] [--report]
    python -m benchmarks.lerf_lift --out OUT --from-json OUT/lerf_lift.json [--note ...] [--report]

OUT holds benchmarks.clip_path's builds of the seeds (the default's package and feature cache). Per seed:
``scale_caches`` cuts and embeds the CLIP stand-in's crop pyramid once per view and writes one feature cache
per scale (that scale's map alone), each is lifted onto the default package's Gaussians
(benchmarks.lift.lift_package, training-free), and so is the default's own cache (the ``lifted`` variant's
targets). ``lerf_quality`` scores them on the held-out views as fmgs.train.evaluate_field scores a served
package: per pixel, each name's rendered dot is its best over the scales' packages (LERF's max over
scales), the argmax is the label; 2D localisation takes each name's relevancy image at its best scale per
pixel, 3D the most relevant Gaussian over the scales. With one package it is evaluate_field exactly.

Distilling a field per scale (or one conditioned on scale) costs a build per scale on this machine; the lift
puts both candidates through the same training-free step, so the row says how the max over scales compares
with the blend when the field is taken out, as the target-map table (CLIP_PATH.md) does before it.
Writes lerf_lift.json and LERF_LIFT.md (with --report, into benchmarks/results/ too).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.clip_variants import STANDIN, variant_name


def scale_caches(data: Path, out: Path, standin: Path) -> tuple[list[Path], list[float]]:
    """One feature cache per scale of the build's crop pyramid (OUT/scale-K, K in the pyramid's order: the
    CLIP stand-in's map of that scale alone, unit-normalised, no DINO target) for every frame of ``data`` at
    the build's map sizes, the crops of each view cut and embedded once. Resumes. Returns the caches and
    the scales (crop edge as a fraction of the image)."""
    from fmgs.data.dataset import load_dataset
    from fmgs.features.cache import FeatureCacheWriter, TargetInfo
    from fmgs.features.extract import ExtractConfig, feature_size
    from fmgs.features.pyramid import pyramid_for, scale_maps
    from fmgs.features.standin import load_standin
    from fmgs.vecmath import safe_normalize

    clip = load_standin(f"standin:{standin}")
    cfg = pyramid_for(clip)
    ds = load_dataset(data)
    dirs = [out / f"scale-{k}" for k in range(len(cfg.scales))]
    info = {"clip": TargetInfo(clip.id, clip.dim, True)}
    writers = [FeatureCacheWriter(d, info) for d in dirs]
    try:
        with torch.inference_mode():
            for i, fr in enumerate(ds.frames):
                if all(w.has(fr.name) for w in writers):
                    continue
                image, _ = ds.image(i)
                sm = scale_maps(clip, image, cfg, feature_size(fr.camera, ExtractConfig().feature_scale))
                for w, m in zip(writers, sm.maps, strict=True):
                    if not w.has(fr.name):
                        w.add(fr.name, clip=safe_normalize(m))
    finally:
        for w in writers:
            w.close()
    return dirs, [float(s) for s in cfg.scales]


class _Views:
    """Per held-out view, what every package renders for the scored names (the engines share Gaussians)."""

    def __init__(self, engines: list) -> None:
        if not engines:
            raise ValueError("no packages to score")
        self.engines = engines

    def labels(self, classes: torch.Tensor, camera) -> np.ndarray:
        """[H,W] served labels: argmax over classes of each class's best rendered dot over the packages."""
        from fmgs.query.segment import class_dots, pixel_labels

        best, alpha = class_dots(self.engines[0], classes, camera)  # the alpha is every engine's
        for e in self.engines[1:]:
            best = torch.maximum(best, class_dots(e, classes, camera)[0])
        return pixel_labels(best, alpha).numpy()

    def peak(self, query: torch.Tensor, camera) -> tuple[int, int]:
        """(x, y) of the pixel whose relevancy, at its best package, is highest (first in row-major order)."""
        from fmgs.query.pose import render_pose

        rel = torch.stack([render_pose(e, camera, query).relevancy for e in self.engines]).amax(0)
        y, x = divmod(int(torch.argmax(rel)), rel.shape[1])
        return x, y

    def top(self, query: torch.Tensor) -> torch.Tensor:
        """The mean [3] of the most relevant Gaussian over the packages (the first package's on ties)."""
        hits = [e.text_query(query, top_k=1) for e in self.engines]
        best = max(range(len(hits)), key=lambda k: (float(hits[k].relevancy[0]), -k))
        e = self.engines[best]
        return e.gaussians.means[int(hits[best].index[0])].double().cpu()


@torch.no_grad()
def lerf_quality(engines: list, ds, encoder, views: list[int], scene_json: Path) -> dict:
    """mIoU, per-class IoU, 2D and 3D localisation of the packages ``engines`` (one per scale, the same
    Gaussians) scored together by the max over scales, on frames ``views`` of a generated scene; with one
    engine, what fmgs.train.evaluate_field.evaluate_field gives."""
    from PIL import Image

    from fmgs.train.evaluate_field import add_overlaps, class_ious

    meta = json.loads(Path(scene_json).read_text())
    names: list[str] = meta["label_names"]
    boxes = {v["file_path"]: v["boxes_2d"] for v in meta["views"]}
    emb = encoder.encode_text(names).float()  # [K,D]
    v = _Views(engines)
    hit2d = n2d = 0
    inter, union = np.zeros(len(names)), np.zeros(len(names))
    for i in views:
        fr = ds.frames[i]
        for name, (x0, y0, x1, y1) in boxes.get(fr.name, {}).items():
            x, y = v.peak(emb[names.index(name)], fr.camera)
            hit2d += x0 <= x <= x1 and y0 <= y <= y1
            n2d += 1
        gt = np.asarray(Image.open(ds.root / "labels" / Path(fr.name).name)).astype(np.int64)
        add_overlaps(v.labels(emb[1:], fr.camera), gt, inter, union)
    hit3d = n3d = 0
    for o in meta["objects"]:
        if o["label"] < 2:
            continue  # the floor is a label, not an object to localise
        p = v.top(emb[names.index(o["name"])]).numpy()
        hit3d += bool(np.all(p >= np.array(o["aabb_min"])) and np.all(p <= np.array(o["aabb_max"])))
        n3d += 1
    ious = class_ious(inter, union, names)
    return {
        "miou": float(np.mean(list(ious.values()))) if ious else 0.0,
        "class_iou": ious,
        "localisation_2d": hit2d / max(n2d, 1),
        "localisation_3d": hit3d / max(n3d, 1),
    }


def language_bytes(packages: list[Path]) -> float:
    """Bytes per embedded Gaussian of the language parts of ``packages`` together (what a package holding
    an embedding per scale would store)."""
    from benchmarks.clip_path import package_bytes

    return float(sum(package_bytes(p)["language_per_embedded"] for p in packages))


def run_seed(out: Path, seed: int, standin: Path, source_variant: str = "dominant") -> dict:
    """Caches, lifts and scores of one seed (each kept once made); the row of lerf_lift.json. The lifts
    take the Gaussians and selection of ``source_variant``'s package ("labels": the label build's, the same
    3DGS and selection rule)."""
    from benchmarks.lift import lift_package
    from fmgs.data import HOLDOUT_EVERY
    from fmgs.data.dataset import load_dataset
    from fmgs.features.text import MiniLMTextEncoder
    from fmgs.query.engine import SceneEngine
    from fmgs.scene.manifest import Manifest

    data = out / f"scene-{seed}"
    name = variant_name(seed, "dominant")
    src = variant_name(seed, source_variant)
    source = out / "models" / src
    features = out / "models" / ".work" / name / "features"
    if not (source / "manifest.json").is_file() or not features.is_dir():
        raise FileNotFoundError(f"seed {seed} needs {source} and {features}: build them first")
    work = out / "lerf" / f"s{seed}"
    t0 = time.process_time()
    caches, scales = scale_caches(data, work / "caches", standin)
    seconds = {"scale maps": time.process_time() - t0}

    def lifted(cache: Path, dest: Path) -> Path:
        if not (dest / "manifest.json").is_file():
            t = time.process_time()
            lift_package(data, source, cache, dest)
            seconds["lift"] = seconds.get("lift", 0.0) + time.process_time() - t
        return dest

    blend = lifted(features, work / "blend")
    per_scale = [lifted(c, work / f"lifted-{c.name}") for c in caches]
    ds = load_dataset(data)
    _, test = ds.split(HOLDOUT_EVERY)
    enc = MiniLMTextEncoder()
    row: dict = {"seed": seed, "scales": scales, "cpu_seconds": seconds, "source": str(source), "kinds": {}}
    # A selected Gaussian no training pixel reaches keeps the source's embedding: the report counts them,
    # and from the label build they would carry the names themselves.
    row["unseen"] = max(Manifest.read(p).extra["lifted"]["unseen"] for p in [blend, *per_scale])
    if row["unseen"] and source_variant == "labels":
        raise ValueError(f"seed {seed}: {row['unseen']} Gaussians would keep the label build's embeddings")
    engines = {p: SceneEngine.open(p) for p in [blend, *per_scale]}
    for kind, pkgs in {"blend": [blend], "max over scales": per_scale}.items():
        q = lerf_quality([engines[p] for p in pkgs], ds, enc, test, data / "scene.json")
        q["language_bytes"] = language_bytes(pkgs)
        q["embedded"] = engines[pkgs[0]].num_embedded
        row["kinds"][kind] = q
    for s, pkg in zip(scales, per_scale, strict=True):  # each scale alone, for the reading
        row["kinds"][f"{s:g} alone"] = lerf_quality([engines[pkg]], ds, enc, test, data / "scene.json")
    return row


KINDS_SHOWN = ("blend", "max over scales")


def _source_words(rows: list[dict]) -> str:
    labels = [Path(r.get("source", "")).name == f"s{r['seed']}" for r in rows]
    if all(labels):
        return "label build (the same 3DGS and selection rule as the default's)"
    return "default build" if not any(labels) else "default or label build"


def _seconds(took: dict[str, float]) -> str:
    done = [f"{k} {v:.0f}" for k, v in took.items() if v > 1.0]  # under a second: made by an earlier run
    return ", ".join(done) or "all made by an earlier run"


def report(d: dict) -> str:
    from benchmarks.common import machine_words

    rows = d["rows"]
    kinds = [k for k in rows[0]["kinds"] if all(k in r["kinds"] for r in rows)]
    seeds = ", ".join(str(r["seed"]) for r in rows)

    def mean(kind: str, key: str) -> float:
        return float(np.mean([r["kinds"][kind][key] for r in rows]))

    lines = [
        "# LERF's scale selection on the Gaussians, lifted",
        "",
        f"Measured {d['machine']['date']} on {machine_words(d['machine'])}, one run of `{d['command']}`.",
        "",
        f"Scenes: CLIP_PATH.md's unseen seeds {seeds}, each with its default build (`dominant`: the blend of "
        "the scales whose crop is at least half the pixel's DINO region). The CLIP stand-in's crop pyramid "
        f"({len(rows[0]['scales'])} scales, crop edges {', '.join(f'{s:g}' for s in rows[0]['scales'])} of "
        "the image) is cut and embedded once per view and each scale's map written as a feature cache of "
        "its own; each cache is lifted without training onto the embedded Gaussians of one package of the "
        "scene (below) "
        "(benchmarks.lift: each Gaussian the blending-weighted mean of the targets of the pixels it "
        "reaches), and so is the default's blended cache. **max over scales** is LERF's query-time scale "
        "selection on those Gaussians: per pixel each name scores its best rendered dot over the scales "
        "(2D: its best relevancy; 3D: the most relevant Gaussian over the scales), what a package with one "
        "embedding per scale would serve; **blend** is the default's targets through the same lift and "
        "the same scorer (CLIP_PATH.md's `lifted` row, made again). Scored on the held-out views with "
        "MiniLM queries: mIoU over the objects and the floor, 2D and 3D localisation as CLIP_PATH.md.",
        "",
        f"Both lifts take the Gaussians and selection of each seed's {_source_words(rows)}; selected "
        f"Gaussians no training pixel reaches (they would keep that package's embedding): "
        f"{max(r.get('unseen', 0) for r in rows)}.",
        "",
        "## Means over the scenes",
        "",
        "| targets, lifted | scenes | 2D loc. | 3D loc. | mIoU | language B / embedded Gaussian |",
        "|---|---:|---:|---:|---:|---:|",
    ]

    def cells(q: dict) -> str:
        return f"{q['localisation_2d']:.3f} | {q['localisation_3d']:.3f} | "

    means = {k: {key: mean(k, key) for key in ("localisation_2d", "localisation_3d", "miou")} for k in kinds}
    for k in KINDS_SHOWN:
        b = mean(k, "language_bytes")
        lines.append(f"| {k} | {len(rows)} | {cells(means[k])}**{means[k]['miou']:.3f}** | {b:.0f} |")
    lines += ["", "Each scale alone, lifted the same way:", "", "| scale | 2D loc. | 3D loc. | mIoU |",
              "|---|---:|---:|---:|"]  # fmt: skip
    lines += [f"| {k} | {cells(means[k])}{means[k]['miou']:.3f} |" for k in kinds if k not in KINDS_SHOWN]
    lines += ["", "## Per scene", "", "| seed | targets, lifted | 2D loc. | 3D loc. | mIoU |",
              "|---|---|---:|---:|---:|"]  # fmt: skip
    for r in rows:
        q = r["kinds"]
        lines += [f"| {r['seed']} | {k} | {cells(q[k])}{q[k]['miou']:.3f} |" for k in KINDS_SHOWN]
    lines += [
        "",
        "CPU seconds of this run per scene (a shared 2-core machine; not comparable with build seconds): "
        + "; ".join(f"seed {r['seed']}: {_seconds(r['cpu_seconds'])}" for r in rows)
        + ".",
        "",
        *[f"- {n}" for n in d.get("notes", [])],
    ]
    return "\n".join(lines).rstrip() + "\n"


def main() -> int:
    from benchmarks.common import command_line, machine

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="benchmarks.clip_path's output folder (the builds)")
    ap.add_argument("--seeds", default="201,202,203")
    ap.add_argument("--standin", default=str(STANDIN), help="the CLIP stand-in's folder")
    ap.add_argument(
        "--source",
        default="dominant",
        help="the variant whose Gaussians are lifted onto "
        "(benchmarks.clip_variants; 'labels': the label build)",
    )
    ap.add_argument("--note", action="append", default=[], help="a line for the report's notes")
    ap.add_argument("--report", action="store_true", help="also write benchmarks/results/LERF_LIFT.md")
    ap.add_argument(
        "--from-json",
        metavar="JSON",
        help="only write the report again from a lerf_lift.json (with --note: appended to its notes)",
    )
    a = ap.parse_args()
    out = Path(a.out)
    if a.from_json:
        d = json.loads(Path(a.from_json).read_text())
        d["notes"] = [*d.get("notes", []), *a.note]
        return _write(d, out, a.report)
    rows = [run_seed(out, int(s), Path(a.standin).resolve(), a.source) for s in a.seeds.split(",")]
    d = {"rows": rows, "machine": {**machine(), "date": time.strftime("%Y-%m-%d")}, "notes": a.note,
         "command": command_line("benchmarks.lerf_lift")}  # fmt: skip
    return _write(d, out, a.report)


def _write(d: dict, out: Path, publish: bool) -> int:
    from benchmarks.common import save_result

    text = report(d)
    save_result(d, out, "LERF_LIFT", text, publish)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
