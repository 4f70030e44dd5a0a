"""The CLIP_PATH variants and how each is built: ``VARIANTS`` (what each sets), ``DESCRIBE`` (the report's
words for them) and ``clip_build`` (the command that makes one variant's package for one scene, run once and
recorded). The report, the scores and the command line are benchmarks.clip_path's.
"""

from __future__ import annotations

import json
import time
from functools import partial
from pathlib import Path

from fmgs.features.sizes import CROP_SCALES
from fmgs.train.config import FieldTrainConfig

ROOT = Path(__file__).resolve().parents[1]
STANDIN = ROOT / "benchmarks" / "standin"
STANDIN_DINO = ROOT / "benchmarks" / "standin_dino"
STANDIN_SEG = ROOT / "benchmarks" / "standin_seg"

VARIANTS: dict[str, dict] = {
    "paper": {"blend": "mean", "dino": True, "dotsim": True},
    "dominant": {"blend": "dominant", "dino": True, "dotsim": True},
    "dominant no-dotsim": {"blend": "dominant", "dino": True, "dotsim": False},
    "coherence": {"blend": "coherence", "dino": True, "dotsim": True},
    "paper no-dotsim": {"blend": "mean", "dino": True, "dotsim": False},
    "paper no-DINO": {"blend": "mean", "dino": False, "dotsim": False},
    "oracle": {"blend": "dominant", "dino": True, "dotsim": True, "oracle": True},
    "oracle paper": {"blend": "mean", "dino": True, "dotsim": True, "oracle": True},
    "region crops": {"blend": "dominant", "dino": True, "dotsim": True, "regions": True},
    "dominant pooled": {"blend": "dominant", "dino": True, "dotsim": True, "pooled": True},
    "segments": {"blend": "dominant", "dino": True, "dotsim": True, "segments": "blend"},
    "segments finest": {"blend": "mean", "dino": True, "dotsim": True, "segments": "finest"},
    "segments finest label masks": {
        "blend": "mean",
        "dino": True,
        "dotsim": True,
        "label_segments": "finest",
    },
    "segments finest label masks balanced": {
        "blend": "mean",
        "dino": True,
        "dotsim": True,
        "features_of": "segments finest label masks",
        "balance": "scale",
    },
    "segments finest label masks no-DINO": {
        "blend": "mean",
        "dino": False,
        "dotsim": False,
        "features_of": "segments finest label masks",
    },
    "dominant 4200 steps": {
        "blend": "dominant",
        "dino": True,
        "dotsim": True,
        "features_of": "dominant",
        "field_steps": FieldTrainConfig.steps,
    },
    "lifted": {"blend": "dominant", "dino": True, "dotsim": False, "features_of": "dominant", "lift": True},
    "dominant photos x2": {"blend": "dominant", "dino": True, "dotsim": True, "photos": 2},
    "dominant finer photos x2": {
        "blend": "dominant",
        "dino": True,
        "dotsim": True,
        "photos": 2,
        "scales": (min(CROP_SCALES) / 2, *CROP_SCALES),
    },
    "labels 4200 steps": {
        "blend": "mean",
        "dino": False,
        "dotsim": False,
        "features_of": "labels",
        "field_steps": FieldTrainConfig.steps,
    },
    "dominant neighbours 1": {
        "blend": "dominant",
        "dino": True,
        "dotsim": True,
        "features_of": "dominant",
        "neighbours": 1,
    },
    "labels neighbours 1": {
        "blend": "mean",
        "dino": False,
        "dotsim": False,
        "features_of": "labels",
        "neighbours": 1,
    },
}
"""The CLIP builds: scale blend (fmgs.features.scale_blend), DINO targets and the dotsim loss. "dominant"
with DINO and dotsim is the build's default. "oracle" variants name every crop without error
(benchmarks.clip_oracle) and distil with ``fmgs train-field``: the method apart from the stand-in; "region
crops" distils benchmarks.region_crops' targets the same way (not a build option), and "label_segments"
benchmarks.label_segments' (the segments variants with the label masks as segments), and "pooled"
``pooled_cache``'s. A variant with
"features_of" distils that variant's feature cache (the same targets) with ``fmgs train-field``, at its own
"field_steps" when it sets them (the product's default steps beside the report's shorter schedule;
"labels": the label build's cache, language loss alone as that build distils it); with
"lift", no field at all: benchmarks.lift's training-free lifting of those targets onto that variant's
Gaussians; with "neighbours" K, that variant's trained field packaged again with ``--embedding-neighbours
K`` (benchmarks.unseen.repackage; its build time is the source's plus the packaging). A variant with
"photos" F cuts its crops from the same views rendered at F times the width and height
(``photos_scene``), its maps stored at the scene's own size: what a user whose photos are larger than the
feature maps gets; with "scales", the pyramid's scales (``--crop-scales``)."""
DESCRIBE = {
    "paper": "the paper's equal mean of the 7 scales, DINO head and dotsim (the FMGS recipe)",
    "dominant": "the default: the scales whose crop is at least half the pixel's DINO region, equally",
    "coherence": "each scale weighed by its crop's DINO coherence with the pixel",
    "oracle": "the default with every crop named without error (benchmarks.clip_oracle), not the stand-in",
    "oracle paper": "the paper's equal mean with every crop named without error",
    "segments": "the default blend pooled within the segmenter stand-in's segments (`--segmenter`, SAM's "
    "role: mask pooling), DINO head and dotsim",
    "segments finest": "the finest scale alone pooled within the same segments (`--segment-map finest`)",
    "segments finest label masks": "the finest scale alone pooled within the label masks, each connected "
    "component a segment (benchmarks.label_segments: the bound a perfect segmenter reaches)",
    "segments finest label masks balanced": "the same targets distilled with `--balance scale` (each term "
    "divided by its targets' mean square per element, so the language term has a voice on the grid)",
    "segments finest label masks no-DINO": "the same targets distilled with the language loss alone "
    "(`--lam 1`, no dotsim), as the label path is",
    "lifted": "the default's targets lifted onto its Gaussians without training (benchmarks.lift: each "
    "Gaussian the blending-weighted mean of the pixels it reaches; no field, no DINO head)",
    "dominant 4200 steps": "the default's targets distilled at the product's default field steps (4,200), "
    "not the report's shorter schedule",
    "labels 4200 steps": "the label path's targets (its feature cache) distilled at the product's 4,200 "
    "field steps, language loss alone as the label build distils them",
    "dominant neighbours 1": "the default's trained field packaged with `--embedding-neighbours 1` (each "
    "Gaussian's stored embedding the field at its mean alone, as in the paper) instead of the default 8",
    "labels neighbours 1": "the label path's trained field packaged with `--embedding-neighbours 1`",
    "dominant photos x2": "the default with its crops cut from the same views rendered at twice the width "
    "and height (benchmarks.clip_variants.photos_scene), the maps stored at the scene's size "
    "(`--feature-side 128`): real photos are larger than the maps, these scenes' 128x96 are smaller",
    "dominant finer photos x2": "dominant photos x2 with one finer scale first (`--crop-scales`, half the "
    "finest crop's edge: 0.025 of the shorter side, 4.8 pixels of the 256x192 views, 25 of a 1000-pixel "
    "photo)",
    "region crops": "one tight crop per DINO-grown region averaged with the finest scale "
    "(benchmarks.region_crops: the mask-based methods' way, DINO regions for masks), DINO head and dotsim",
    "dominant pooled": "the default blend pooled within DINO-coherent neighbourhoods "
    "(fmgs.features.scale_blend.pool_regions, a square of a tenth of the shorter side, each neighbour "
    "weighed by its squared DINO cosine with the pixel; benchmarks.clip_variants.pooled_cache), DINO head "
    "and dotsim",
}


def variant_name(seed: int, variant: str) -> str:
    """The package name of ``variant`` on scene ``seed``; "labels": the label build's (``s{seed}``)."""
    return f"s{seed}" if variant == "labels" else f"s{seed}-" + variant.replace(" ", "-")


def build_record(out: Path, seed: int, variant: str) -> Path:
    """OUT's record of how ``variant``'s package for scene ``seed`` was made (its command and seconds);
    benchmarks.unseen.build_scene names the label build's by the seed alone."""
    return out / f"build-{seed if variant == 'labels' else variant_name(seed, variant)}.json"


def clip_build(
    out: Path,
    seed: int,
    data: Path,
    variant: str,
    field_steps: int | None,
    standin: Path,
    dino: Path,
    threads: int = 0,
) -> Path:
    """``fmgs build --targets clip`` of ``variant`` on the label build's 3DGS (an oracle variant: its feature
    cache, then ``fmgs train-field`` on that 3DGS); returns the package. ``threads``: the field's CPU
    threads (0: the build's own choice)."""
    from fmgs.cli import main as fmgs

    v = VARIANTS[variant]
    name = variant_name(seed, variant)
    ply = out / "models" / ".work" / f"s{seed}" / "gs" / "point_cloud.ply"
    prepare = None  # what the command needs first
    field_steps = v.get("field_steps", field_steps)
    if v.get("features_of"):  # another variant's targets: distilled again, or lifted onto its Gaussians
        src = variant_name(seed, v["features_of"])
        source, features = out / "models" / src, out / "models" / ".work" / src / "features"
        if not features.is_dir() or (v.get("lift") and not (source / "manifest.json").is_file()):
            raise FileNotFoundError(f"{name} needs {source} and {features}: build {v['features_of']!r} first")
        if v.get("neighbours"):  # the same field, packaged again
            return _repackaged(out, seed, variant, v["features_of"], v["neighbours"])
        if v.get("lift"):  # nothing trained
            from benchmarks.lift import lift_package

            cmd = ["python", "-m", "benchmarks.lift", str(data), "--source", str(source), "--features",
                   str(features), "--out", str(out / "models" / name)]  # fmt: skip
            return _recorded(
                out, name, cmd, partial(lift_package, data, source, features, out / "models" / name)
            )
        field = out / "models" / ".work" / name / "field"
        cmd = ["train-field", str(data), "--gaussians", str(ply), "--features", str(features),
               "--out", str(field), "--package", str(out / "models" / name)]  # fmt: skip
        if not v["dino"]:  # the language loss alone (the cache's DINO targets weigh nothing)
            cmd += ["--lam", "1"]
        if v.get("balance"):
            cmd += ["--balance", v["balance"]]
        threads_flag = "--threads"
    elif v.get("oracle") or v.get("regions") or v.get("label_segments") or v.get("pooled"):  # cache here
        from benchmarks.clip_oracle import oracle_cache
        from benchmarks.label_segments import label_segments_cache
        from benchmarks.region_crops import region_cache

        work = out / "models" / ".work" / name
        cmd = ["train-field", str(data), "--gaussians", str(ply), "--features", str(work / "features"),
               "--out", str(work / "field"), "--package", str(out / "models" / name)]  # fmt: skip
        threads_flag = "--threads"
        if v.get("regions"):
            prepare = partial(region_cache, data, work / "features", standin, dino, v["blend"])
        elif v.get("pooled"):
            prepare = partial(pooled_cache, data, work / "features", standin, dino, v["blend"])
        elif v.get("label_segments"):
            seg_map = v["label_segments"]
            prepare = partial(label_segments_cache, data, work / "features", standin, dino, seg_map)
        else:
            prepare = partial(
                oracle_cache, data, work / "features", standin, dino if v["dino"] else None, v["blend"]
            )
    else:
        src, sized = data, []
        if v.get("photos"):  # a larger scene, made before the build; the maps at the scene's own size
            src = out / f"{data.name}-x{v['photos']}"
            prepare = partial(photos_scene, data, src, v["photos"])
            c = json.loads((data / "scene.json").read_text())["config"]
            sized = ["--feature-side", str(max(c["width"], c["height"]))]
        cmd = ["build", str(src), "--name", name, "--models", str(out / "models"), "--targets", "clip",
               "--clip-model", f"standin:{standin}", "--ply", str(ply), "--scale-blend", v["blend"],
               "--dino-model", f"standin-dino:{dino}" if v["dino"] else "none", *sized]  # fmt: skip
        if v.get("scales"):
            cmd += ["--crop-scales", ",".join(str(c) for c in v["scales"])]
        if v.get("segments"):
            cmd += ["--segmenter", f"standin-seg:{STANDIN_SEG}"]
            if v["segments"] == "finest":
                cmd += ["--segment-map", "finest"]
        threads_flag = "--field-threads"
    if not v["dotsim"]:
        cmd.append("--no-dotsim")
    if field_steps is not None:
        cmd += ["--field-steps", str(field_steps)]
    if threads:
        cmd += [threads_flag, str(threads)]

    def run() -> None:
        if prepare is not None:
            prepare()
        assert fmgs(cmd) == 0

    return _recorded(out, name, cmd, run)


def pooled_cache(data: Path, cache_dir: Path, standin: Path, dino: Path, blend: str) -> Path:
    """A feature cache of ``data`` as ``fmgs build --scale-blend blend`` writes it, each CLIP target then
    pooled within DINO-coherent neighbourhoods (``pool_regions`` over a square of POOL_RADIUS of the map's
    shorter side, the target maps' "+ pooled" candidates in benchmarks.clip_targets), and the DINO
    stand-in's map (benchmarks.clip_oracle.write_cache)."""
    from benchmarks.clip_oracle import write_cache
    from benchmarks.clip_targets import POOL_RADIUS
    from fmgs.features.dino import load_dense_encoder
    from fmgs.features.pyramid import hybrid_map, pyramid_for
    from fmgs.features.scale_blend import pool_regions
    from fmgs.features.standin import load_standin

    clip = load_standin(f"standin:{standin}")
    cfg = pyramid_for(clip, blend=blend)

    def target(fr, image, hw, dense):
        radius = max(1, round(POOL_RADIUS * min(hw)))
        return pool_regions(hybrid_map(clip, image, cfg, hw, dense=dense), dense, radius)

    return write_cache(data, cache_dir, clip, load_dense_encoder(f"standin-dino:{dino}"), target)


def photos_scene(data: Path, photos: Path, factor: int) -> Path:
    """``photos``: the synthetic scene ``data`` generated again from its recorded config with width and height
    times ``factor`` (the same objects, poses and points: checked); returns ``photos``."""
    import numpy as np

    from fmgs.cli import main as fmgs

    scene = json.loads((data / "scene.json").read_text())
    c = scene["config"]
    if not (photos / "scene.json").is_file():
        cmd = ["synth", "--out", str(photos), "--preset", c["preset"], "--objects", str(c["objects"]),
               "--seed", str(c["seed"]), "--views", str(c["views"]), "--novel", str(c["novel"]),
               "--backdrop", c["backdrop"], "--rig", c["rig"], "--points", str(c["points"]),
               "--size", f"{c['width'] * factor}x{c['height'] * factor}"]  # fmt: skip
        if any(c["distortion"]):
            cmd += ["--distortion", ",".join(str(k) for k in c["distortion"])]
        assert fmgs(cmd) == 0
    frames = [json.loads((d / "transforms.json").read_text())["frames"] for d in (data, photos)]
    pairs = zip(*frames, strict=True)
    same = [np.array_equal(a["transform_matrix"], b["transform_matrix"]) for a, b in pairs]
    same.append(scene["objects"] == json.loads((photos / "scene.json").read_text())["objects"])
    if not all(same):
        raise ValueError(f"{photos} does not show {data}'s scene at {factor}x: generate it again")
    return photos


def _repackaged(out: Path, seed: int, variant: str, source: str, neighbours: int) -> Path:
    """``variant``'s package: variant ``source``'s trained field packaged again with ``neighbours``
    (recorded; the seconds are the source's build and this packaging)."""
    from benchmarks.unseen import repackage
    from fmgs.features.text import load_text_encoder

    name, src = variant_name(seed, variant), out / "models" / variant_name(seed, source)
    if not (src / "manifest.json").is_file():
        raise FileNotFoundError(f"{name} needs {src}: build it first")
    enc = load_text_encoder(json.loads((src / "manifest.json").read_text())["encoder"]["id"])
    cmd = ["benchmarks.unseen.repackage", str(src), str(out / "models" / name), str(neighbours)]  # a call
    took = json.loads(build_record(out, seed, source).read_text())["seconds"]
    run = partial(repackage, src, out / "models" / name, neighbours, enc)
    return _recorded(out, name, cmd, run, took)


def _recorded(out: Path, name: str, cmd: list[str], run, plus: float = 0.0) -> Path:
    """Package OUT/models/NAME, made by ``run()`` unless OUT/build-NAME.json records ``cmd`` made it; the
    record keeps the seconds it took (and ``plus``: what made its source)."""
    record = out / f"build-{name}.json"
    if record.is_file() and json.loads(record.read_text())["command"] == cmd:
        return out / "models" / name
    t0 = time.perf_counter()
    run()
    record.write_text(json.dumps({"seconds": plus + time.perf_counter() - t0, "command": cmd}))
    return out / "models" / name
