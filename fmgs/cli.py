"""The ``fmgs`` command line: thin wrappers over the library."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path


def _load_scene(path: Path):
    from fmgs.errors import ValidationError
    from fmgs.io.ply import read_ply
    from fmgs.io.tensors import load_gaussians

    if path.is_dir():
        found = sorted(
            str(p.relative_to(path))
            for p in path.glob("**/*")
            if p.suffix in (".ply", ".splat", ".safetensors")
        )
        hint = f"; it holds {', '.join(found[:3])}" if found else ""
        raise ValidationError(
            str(path), f"is a folder: pass a scene file (.ply, .splat or .safetensors){hint}"
        )
    return load_gaussians(path) if path.suffix == ".safetensors" else read_ply(path)


def cmd_info(args: argparse.Namespace) -> int:
    """Validate a scene file and print its size, SH degree, bounds and opacity statistics; or describe a
    scene package folder from its manifest."""
    from fmgs.scene.manifest import FILENAME

    if Path(args.scene).is_dir() and (Path(args.scene) / FILENAME).is_file():
        print(json.dumps(_package_info(Path(args.scene)), indent=2))
        return 0
    g = _load_scene(Path(args.scene))
    lo, hi = g.means.min(0).values.tolist(), g.means.max(0).values.tolist()
    op = g.opacities
    info = {
        "file": str(args.scene),
        "gaussians": g.num,
        "sh_degree": g.sh_degree,
        "bounds_min": [round(v, 4) for v in lo],
        "bounds_max": [round(v, 4) for v in hi],
        "opacity_median": round(float(op.median()), 4),
        "opacity_above_0.25": int((op > 0.25).sum()),
    }
    print(json.dumps(info, indent=2))
    return 0


PACKAGE_BUILD_KEYS = ("description", "source", "build_seconds", "made_by", "targets", "embedding_neighbours")
"""Keys of a package manifest's ``extra`` that ``fmgs info`` shows as how the package was built."""


def _package_info(path: Path) -> dict:
    """What a scene package holds, from its manifest (validated; no tensor is read): name, encoder, counts,
    bounds, the field's storage, label names, how it was built, and its files with their sizes."""
    from fmgs.errors import ValidationError
    from fmgs.scene.manifest import Manifest

    m = Manifest.read(path)
    missing = [f for f in ("gaussians.safetensors", "embeddings.safetensors") if not (path / f).is_file()]
    if missing:
        raise ValidationError(str(path), f"scene package without {', '.join(missing)}")
    build = {k: m.extra[k] for k in PACKAGE_BUILD_KEYS if k in m.extra}
    enc = m.extra.get("text_encoder")
    if isinstance(enc, dict) and enc.get("revision"):
        build["text_encoder_revision"] = enc["revision"]
    return {
        "package": str(path),
        "name": m.name,
        "encoder": {"id": m.encoder_id, "dim": m.dim},
        "gaussians": m.num_gaussians,
        "embedded": m.num_selected,
        "sh_degree": m.sh_degree,
        "bounds_min": [round(v, 4) for v in m.bounds[:3]],
        "bounds_max": [round(v, 4) for v in m.bounds[3:]],
        "embedding_dtype": m.embedding_dtype,
        "field": None if m.field is None else {"dtype": m.field.dtype, "dino_head": m.field.dino_head},
        "label_names": list(m.label_names),
        "build": build,
        "files": {p.name: p.stat().st_size for p in sorted(path.iterdir()) if p.is_file()},
    }


def cmd_render(args: argparse.Namespace) -> int:
    """Render one camera of a dataset (any layout fmgs reads, undistorted like training) to a PNG."""
    import numpy as np
    import torch
    from PIL import Image

    from fmgs.render.rgb import render_rgb

    g = _load_scene(Path(args.scene))
    cam = _render_camera(args).scaled(args.scale)
    t0 = time.perf_counter()
    with torch.no_grad():
        out = render_rgb(g, cam, background=torch.zeros(3), backend=args.backend)
    dt = time.perf_counter() - t0
    img = (out.image.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    Image.fromarray(img).save(args.out)
    print(
        f"wrote {args.out} ({cam.name}, {cam.width}x{cam.height}, {dt * 1000:.1f} ms, backend {args.backend})"
    )
    return 0


def _render_camera(args: argparse.Namespace):
    """The camera ``--frame`` (index or image name) names: frames numbered as every command numbers
    them (sorted by name, those with an image); a transforms.json with no image at all is a camera path,
    numbered in its listed order."""
    import logging

    from fmgs.data.dataset import load_dataset
    from fmgs.data.transforms import parse_transforms
    from fmgs.errors import ValidationError

    src = Path(args.transforms)
    if src.is_dir() and (src / "transforms.json").is_file() and not (src / "sparse").exists():
        src = src / "transforms.json"
    cams = None
    if src.is_file() and src.suffix == ".json":
        if not parse_transforms(src).frames:  # a camera path: no photos to number by
            parsed = parse_transforms(src, keep_missing=True)
            if any(not f.lens.is_pinhole for f in parsed.frames):
                logging.getLogger("fmgs").warning("%s: lens distortion ignored (renders are pinhole)", src)
            cams = [f.camera for f in parsed.frames]
    if cams is None:
        cams = [f.camera for f in load_dataset(src, undistort_dir=args.undistort_dir).frames]
    names = [c.name for c in cams]
    frame = args.frame
    if frame.lstrip("-").isdigit():
        i = int(frame)
        if not 0 <= i < len(cams):
            raise ValidationError(
                "--frame", f"{i} is out of range: {src} has {len(cams)} frames (0..{len(cams) - 1})"
            )
        return cams[i]
    if frame in names:
        return cams[names.index(frame)]
    matches = [i for i, n in enumerate(names) if Path(n).name == frame]
    if len(matches) == 1:
        return cams[matches[0]]
    raise ValidationError("--frame", f"no frame named {frame!r} in {src} (first: {names[:3]})")


def _numbers(flag: str, text: str, count: int, expected: str) -> tuple[float, ...]:
    """``count`` comma-separated numbers from a flag's text; ValidationError naming the flag otherwise."""
    from fmgs.errors import ValidationError

    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != count:
        raise ValidationError(flag, f"expected {expected}, got {text!r}")
    return values


def cmd_synth(args: argparse.Namespace) -> int:
    """Render a synthetic labelled scene (Open3D ray casting) as a transforms.json dataset."""
    from fmgs.synth import SynthConfig, generate

    w, h = (int(v) for v in args.size.lower().split("x"))
    dist = _numbers("--distortion", args.distortion, 4, "four numbers k1,k2,p1,p2")
    cfg = SynthConfig(
        views=args.views,
        width=w,
        height=h,
        objects=args.objects,
        seed=args.seed,
        points=args.points,
        distortion=dist,
        preset=args.preset,
        novel=args.novel,
        rig=args.rig,
        backdrop=args.backdrop,
        declare_background=not args.undeclared_background,
    )
    t0 = time.perf_counter()
    path = generate(args.out, cfg)
    secs = time.perf_counter() - t0
    print(f"wrote {path} ({cfg.views} views, {w}x{h}, {cfg.objects} objects) in {secs:.1f} s")
    return 0


def cmd_sfm(args: argparse.Namespace) -> int:
    """Photos to poses: pycolmap SfM, then undistortion into a dataset folder."""
    import logging

    from fmgs.sfm import run_sfm
    from fmgs.sfm.config import SfMConfig

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = _settings(args, SfMConfig)
    if args.per_image_camera:
        cfg = replace(cfg, single_camera=False)
    r = run_sfm(args.images, args.out, cfg)
    params = ",".join(f"{v:.6g}" for v in r.camera_params)
    cams = f"{r.cameras} cameras, first " if r.cameras > 1 else ""
    print(
        f"registered {r.registered}/{r.total} photos, {r.points} points, mean reprojection error "
        f"{r.mean_reprojection_error:.3f} px, {r.seconds:.0f} s\n"
        f"camera: {cams}{r.camera_model} {params} (focal from {r.focal_source})\n"
        f"dataset: {r.dataset_dir}; COLMAP's log: {Path(args.out) / 'colmap.log'}"
    )
    return 0


def cmd_train_gs(args: argparse.Namespace) -> int:
    """Train 3D Gaussian Splatting on a posed dataset and write point_cloud.ply."""
    from fmgs.data.dataset import load_dataset
    from fmgs.train.gaussians import train_gaussians

    cfg = _gs_config(args)
    ds = load_dataset(args.data, undistort_dir=args.undistort_dir)
    res = train_gaussians(ds, args.out, cfg, resume=not args.restart)
    print(
        f"trained {res.steps} steps in {res.seconds:.0f} s: {res.gaussians.num} Gaussians, "
        f"final loss {res.final_loss:.4f}; wrote {Path(args.out) / 'point_cloud.ply'}"
    )
    return 0


def cmd_eval_gs(args: argparse.Namespace) -> int:
    """PSNR and SSIM of a 3DGS scene on the dataset's held-out views."""
    from fmgs.data.dataset import load_dataset
    from fmgs.train.evaluate import evaluate
    from fmgs.train.floaters import floater_mask
    from fmgs.train.gaussians import dataset_background, trained_background

    ds = load_dataset(args.data, undistort_dir=args.undistort_dir)
    g = _load_scene(Path(args.scene))
    if args.background == "auto":  # what the scene was trained with (its train.json), else the dataset's
        scene = Path(args.scene)
        bg = trained_background(scene.parent, ds) if scene.is_file() else dataset_background(ds)
    else:
        bg = _numbers("--background", args.background, 3, "auto or R,G,B in [0,1]")
    res = evaluate(g, ds, args.out, scale=args.scale, background=bg, progress=True)
    print(res.table())
    print(floater_mask(g, ds)[1].line())
    if res.warning():
        print(f"warning: {res.warning()}")
    if args.out:
        print(
            f"wrote {Path(args.out) / 'eval.json'} and side-by-side renders in {Path(args.out) / 'renders'}"
        )
    return 0


# Settings of each stage come from its config dataclass: every field is a flag (fmgs/flags.py) and a key
# of the --config TOML file; the aliases keep the short names the commands have always had.
GS_ALIASES = {"image_scale": "--scale", "densify.grad_threshold": "--grad-threshold"}
TARGET_ALIASES = {"kind": "--targets"}
FIELD_ALIASES = {"steps": "--field-steps"}
BUILD_ALIASES = {
    "gs.image_scale": "--gs-scale",
    "gs.sh_degree": "--sh-degree",
    "gs.densify.grad_threshold": "--grad-threshold",
    "targets.kind": "--targets",
    **{
        f"targets.{k}": "--" + k.replace("_", "-")
        for k in (
            "clip_model",
            "dino_model",
            "single_scale",
            "crop_stride",
            "labels",
            "names",
            "text_encoder",
            "feature_scale",
            "feature_side",
        )
    },
    "field.per_gaussian": "--per-gaussian",
    "field.adaptive_resolution": "--adaptive-resolution",
    "field.seed": "--seed",
}
AUTO_DEVICE = {"device": "auto"}
"""The commands pick the GPU when there is one (the library's configs default to the CPU)."""
_BUILD_STAGE_OWNED = ("gs.device", "field.device")
"""Set from the build's own ``device`` for every stage."""


def _settings(args, cls, defaults=None, base=None):
    from fmgs import flags
    from fmgs.errors import ValidationError

    try:
        values = flags.values_from(cls, args, args.config, defaults)
        where = str(args.config or "flags")
        cfg = flags.build(cls, values, where)  # validates every value
        if base is not None:  # then the same settings over a base derived from them
            cfg = flags.build(cls, values, where, base(cfg))
    except ValueError as e:
        raise ValidationError("settings", str(e)) from e
    if getattr(cfg, "device", None) == "auto":
        cfg = replace(cfg, device=_auto_device())
    return cfg


def _gs_config(args: argparse.Namespace):
    from fmgs.train.config import GSTrainConfig

    # Fewer steps compress the SH and densification schedule (reduced() is the default at 30,000).
    return _settings(args, GSTrainConfig, AUTO_DEVICE, lambda c: GSTrainConfig.reduced(c.steps))


def _target_spec(args: argparse.Namespace):
    from fmgs.build.config import TargetSpec

    return _settings(args, TargetSpec)


def _field_config(args: argparse.Namespace):
    from fmgs.train.config import FieldTrainConfig

    # Fewer steps compress the schedule (dotsim starts at the same fraction).
    cfg = _settings(args, FieldTrainConfig, AUTO_DEVICE, lambda c: FieldTrainConfig().reduced(c.steps))
    return replace(cfg, dotsim_weight=0.0) if args.no_dotsim else cfg


def cmd_features(args: argparse.Namespace) -> int:
    """Extract feature targets (hybrid CLIP + DINO, or label masks) of a posed dataset into a cache."""
    from fmgs.build import extract_features
    from fmgs.data.dataset import load_dataset

    if args.ray is not None:
        from fmgs.features.distributed import TargetJob, extract_features_ray

        job = TargetJob(str(args.data), _target_spec(args), args.device, args.undistort_dir)
        cache = extract_features_ray(job, Path(args.out), None if args.ray == "local" else args.ray)
    else:
        ds = load_dataset(args.data, undistort_dir=args.undistort_dir)
        cache = extract_features(ds, Path(args.out), _target_spec(args), args.device)
    t = {k: f"{v.encoder} ({v.dim}-D)" for k, v in cache.targets.items()}
    print(f"feature cache {args.out}: {len(cache.image_names)} images, targets {t}")
    return 0


def cmd_train_field(args: argparse.Namespace) -> int:
    """Distil a feature cache into the field over a frozen 3DGS scene; optionally write a package."""
    from fmgs.build import package_from_field
    from fmgs.data.dataset import load_dataset
    from fmgs.features.cache import FeatureCache
    from fmgs.features.text import load_text_encoder
    from fmgs.train.field import train_field

    ds = load_dataset(args.data, undistort_dir=args.undistort_dir)
    g = _load_scene(Path(args.gaussians))
    cache = FeatureCache.open(args.features)
    res = train_field(g, ds, cache, args.out, _field_config(args), resume=not args.restart)
    print(
        f"trained {len(res.losses)} steps in {res.seconds:.0f} s on {len(res.selection.index)} of "
        f"{res.selection.total} Gaussians ({100 * res.selection.fraction:.0f}%), "
        f"final loss {res.losses[-1]:.3g}"
    )
    if args.package:
        enc = load_text_encoder(cache.targets["clip"].encoder)
        out = package_from_field(
            args.package,
            g,
            res,
            enc,
            include_dino=args.include_dino,
            field_dtype=args.field_dtype,
            neighbours=args.embedding_neighbours,
        )
        print(f"wrote scene package {out}")
    return 0


def _build_config(args: argparse.Namespace):
    """BuildConfig from the flags, the --config file and --extra (fewer steps compress a stage)."""
    from fmgs.build.config import BuildConfig
    from fmgs.errors import ValidationError

    def base(c):  # fewer steps compress each stage's schedule
        return BuildConfig.scheduled(c.name, c.gs.steps, c.field.steps)

    cfg = _settings(args, BuildConfig, AUTO_DEVICE, base)
    if args.no_dotsim:
        cfg = replace(cfg, field=replace(cfg.field, dotsim_weight=0.0))
    if args.extra_file:
        try:
            extra = json.loads(Path(args.extra_file).read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise ValidationError("--extra", f"cannot read {args.extra_file} ({e})") from e
        if not isinstance(extra, dict):
            raise ValidationError("--extra", f"{args.extra_file} must hold a JSON object")
        cfg = replace(cfg, extra={**cfg.extra, **extra})
    return cfg


def cmd_shard(args: argparse.Namespace) -> int:
    """Split a scene package into spatial shards (each a package) with a shard manifest."""
    from fmgs.scene.shards import ShardManifest, write_shards

    src = Path(args.package)
    out = Path(args.out) if args.out else src.parent / f"{src.name}-{args.shards}shards"
    t0 = time.perf_counter()
    write_shards(src, out, args.shards)
    sm = ShardManifest.read(out)
    rows = [f"  {s.folder}: {s.num_gaussians} Gaussians, {s.num_selected} embedded" for s in sm.shards]
    print(f"{out}: {len(sm.shards)} shards of {sm.name} in {time.perf_counter() - t0:.1f} s", *rows, sep="\n")
    return 0


def cmd_build(args: argparse.Namespace) -> int:
    """Photos (or a posed dataset, or a .ply with its posed images) to a scene package in models/."""
    from fmgs.build import build_scene

    cfg = _build_config(args)
    if args.offline:  # read at each model load, here and in Ray workers started from this process
        os.environ["FMGS_OFFLINE"] = "1"
    out = build_scene(args.source, cfg)
    print(f"wrote scene package {out}")
    return 0


def _config_flag(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument(
        "--config",
        metavar="TOML",
        help=f"{what} settings from a TOML file (keys: the long flag names with _ for -, tables for the "
        "nested groups); flags given on the command line win",
    )


def _add_package_args(p: argparse.ArgumentParser) -> None:
    from fmgs.build.config import EMBEDDING_NEIGHBOURS, MAX_EMBEDDING_NEIGHBOURS

    p.add_argument("--include-dino", action="store_true", help="keep the DINO head in the package")
    p.add_argument(
        "--field-dtype",
        default="float32",
        choices=["float32", "float16"],
        help="storage of the field's table and heads in the package (float16: half the size)",
    )
    p.add_argument(
        "--embedding-neighbours",
        type=int,
        default=EMBEDDING_NEIGHBOURS,
        metavar="K",
        help="each stored embedding of a Gaussian whose K-1 nearest embedded Gaussians all lie within "
        "twice its largest scale is the mean over them and itself, so a query's best Gaussians lie in an "
        "object's midst; others keep their own (1: the field at each mean alone, as in the paper; "
        f"1..{MAX_EMBEDDING_NEIGHBOURS}; default {EMBEDDING_NEIGHBOURS})",
    )


def _undistort_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--undistort-dir",
        help="where the undistorted copy of a dataset with lens distortion goes (default: "
        "fmgs_undistorted/ beside the dataset; made once, reused while the dataset is unchanged)",
    )


def _no_dotsim(p) -> None:
    p.add_argument("--no-dotsim", action="store_true", help="ablation: no dot-product-similarity loss")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="fmgs", description="FMGS: foundation-model embedded 3D Gaussian Splatting"
    )
    sub = p.add_subparsers(dest="command", required=True)
    from fmgs import flags
    from fmgs.build.config import BuildConfig, TargetSpec
    from fmgs.sfm.config import SfMConfig
    from fmgs.synth import BACKDROPS, PRESETS, RIGS
    from fmgs.train.config import FieldTrainConfig, GSTrainConfig

    i = sub.add_parser(
        "info",
        help="validate a scene (.ply, .splat or .safetensors) and print a summary, or describe a scene "
        "package folder (e.g. models/demo)",
    )
    i.add_argument("scene", help="scene file, or scene package folder")
    i.set_defaults(func=cmd_info)
    r = sub.add_parser(
        "render", help="render a camera of a dataset (or of a camera-path transforms.json) to PNG"
    )
    r.add_argument("scene", help="3DGS .ply (graphdeco or compressed), .splat, or fmgs .safetensors")
    r.add_argument(
        "--transforms",
        "--data",
        dest="transforms",
        required=True,
        help="dataset folder or transforms.json with the camera (undistorted as for training)",
    )
    r.add_argument(
        "--frame",
        default="0",
        help="frame index (the order every command uses: sorted by name) or image name",
    )
    _undistort_flag(r)
    r.add_argument("--scale", type=float, default=1.0, help="resize the image by this factor")
    r.add_argument("--backend", default="auto", choices=["auto", "reference", "cpu", "cuda"])
    r.add_argument("--out", default="render.png")
    r.set_defaults(func=cmd_render)
    sy = sub.add_parser("synth", help="render a synthetic labelled scene (RGB, depth, labels, boxes)")
    sy.add_argument("--out", required=True)
    sy.add_argument("--views", type=int, default=32)
    sy.add_argument("--size", default="128x96", help="WxH")
    sy.add_argument("--objects", type=int, default=6)
    sy.add_argument("--seed", type=int, default=0, help="object choice (cluttered), sizes and layout")
    sy.add_argument(
        "--preset",
        default="basic",
        choices=PRESETS,
        help="basic: the first objects, spread apart; cluttered: a seeded choice of up to 13 objects "
        "(thin, small, flat), about half touching another, on a striped floor; world: up to 15 objects of "
        "distinct shapes named by colour, texture and shape (fmgs.synthworld), small to large",
    )
    sy.add_argument(
        "--novel",
        type=int,
        default=0,
        help="world preset: this many objects take a held-out colour-shape pair (default 0: none)",
    )
    sy.add_argument("--points", type=int, default=20_000, help="surface samples in points3D.ply")
    sy.add_argument(
        "--distortion",
        default="0,0,0,0",
        metavar="K1,K2,P1,P2",
        help="render through an OpenCV lens with these coefficients (written to transforms.json)",
    )
    sy.add_argument(
        "--rig",
        default="ring",
        choices=RIGS,
        help="ring (default): cameras on one ring at two heights; grazing: every third camera on a low "
        "ring looking across the floor, where the backdrop fills the upper image",
    )
    sy.add_argument(
        "--backdrop",
        default="constant",
        choices=BACKDROPS,
        help="constant (default): one colour behind the scene; walls: a textured round wall around the floor "
        "(labelled background, sampled into the sparse points) with the constant colour above it",
    )
    sy.add_argument(
        "--undeclared-background",
        action="store_true",
        help="leave the constant backdrop colour out of transforms.json (default: declared as "
        '"background"), as most real captures do',
    )
    sy.set_defaults(func=cmd_synth)
    sf = sub.add_parser("sfm", help="photos to poses with pycolmap; writes OUT/undistorted (a dataset)")
    sf.add_argument("images", help="folder of photos")
    sf.add_argument("--out", required=True)
    sf.add_argument("--per-image-camera", action="store_true", help="one camera per photo (mixed devices)")
    _config_flag(sf, "structure-from-motion")
    flags.add_flags(sf.add_argument_group("structure from motion (SfMConfig)"), SfMConfig)
    sf.set_defaults(func=cmd_sfm)

    t = sub.add_parser("train-gs", help="train 3D Gaussian Splatting on a posed dataset")
    t.add_argument("data", help="dataset folder (transforms.json or COLMAP sparse/0 + images/)")
    t.add_argument("--out", required=True)
    _undistort_flag(t)
    t.add_argument("--restart", action="store_true", help="ignore an existing checkpoint in --out")
    _config_flag(t, "training")
    g = t.add_argument_group("training (GSTrainConfig; fewer --steps compress the SH and densify schedule)")
    flags.add_flags(g, GSTrainConfig, aliases=GS_ALIASES, defaults=AUTO_DEVICE)
    t.set_defaults(func=cmd_train_gs)
    e = sub.add_parser("eval-gs", help="PSNR/SSIM on the held-out views (every 8th image)")
    e.add_argument("data")
    e.add_argument("scene", help="trained .ply, .splat or .safetensors")
    e.add_argument("--out", help="folder for eval.json, eval.md and side-by-side renders")
    e.add_argument("--scale", type=float, default=1.0)
    e.add_argument(
        "--background",
        default="auto",
        metavar="auto|R,G,B",
        help="colour behind the Gaussians (default auto: the one the scene trained with, from train.json "
        "beside it, else the dataset's declared one, else black)",
    )
    _undistort_flag(e)
    e.set_defaults(func=cmd_eval_gs)
    fe = sub.add_parser("features", help="extract feature targets of a posed dataset into a cache")
    fe.add_argument("data", help="posed dataset folder")
    fe.add_argument("--out", required=True, help="feature cache folder")
    fe.add_argument("--device", default="auto", help="torch device (auto: cuda when available)")
    fe.add_argument(
        "--ray",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="extract on a Ray cluster's workers (needs fmgs[ray]; GPUs where it has them): ADDRESS of a "
        "running cluster ('auto' finds the local node's), or none to start a local one",
    )
    _undistort_flag(fe)
    _config_flag(fe, "target")
    flags.add_flags(fe.add_argument_group("targets (TargetSpec)"), TargetSpec, aliases=TARGET_ALIASES)
    fe.set_defaults(func=cmd_features)
    tf = sub.add_parser("train-field", help="distil a feature cache into the feature field")
    tf.add_argument("data", help="posed dataset folder")
    tf.add_argument("--gaussians", required=True, help="frozen 3DGS scene (.ply, .splat or .safetensors)")
    tf.add_argument("--features", required=True, help="feature cache folder")
    tf.add_argument("--out", required=True, help="folder for the checkpoint and field_train.json")
    tf.add_argument("--package", help="also write a scene package to this folder (e.g. models/NAME)")
    _undistort_flag(tf)
    _add_package_args(tf)
    tf.add_argument("--restart", action="store_true", help="ignore an existing checkpoint in --out")
    _config_flag(tf, "distillation")
    g = tf.add_argument_group("distillation (FieldTrainConfig; fewer --field-steps compress the schedule)")
    flags.add_flags(g, FieldTrainConfig, aliases=FIELD_ALIASES, defaults=AUTO_DEVICE)
    _no_dotsim(g)
    tf.set_defaults(func=cmd_train_field)
    b = sub.add_parser("build", help="photos or a posed dataset -> scene package in models/")
    b.add_argument("source", help="photo folder, or posed dataset folder")
    b.add_argument(
        "--extra", dest="extra_file", help="JSON file with an object merged into the manifest's extra"
    )
    b.add_argument(
        "--offline",
        action="store_true",
        help="never download models: use local folders and the hub cache only (as HF_HUB_OFFLINE=1 does); "
        "a missing model stops the build naming the command that fetches it",
    )
    _config_flag(b, "build")
    g = b.add_argument_group(
        "build (BuildConfig: the gs-, targets- and field- groups are the stages' settings; fewer "
        "--gs-steps or --field-steps compress that stage's schedule)"
    )
    flags.add_flags(g, BuildConfig, aliases=BUILD_ALIASES, defaults=AUTO_DEVICE, skip=_BUILD_STAGE_OWNED)
    _no_dotsim(g)
    b.set_defaults(func=cmd_build)

    sh = sub.add_parser(
        "shard",
        help="split a scene package into K spatial shards (a balanced k-d split of the means) for serving "
        "a scene bigger than one node on a Ray cluster",
    )
    sh.add_argument("package", help="scene package folder, e.g. models/NAME")
    sh.add_argument("--shards", type=int, required=True, help="number of shards K (1..4096)")
    sh.add_argument("--out", help="folder for the sharded scene (default: PACKAGE-Kshards beside it)")
    sh.set_defaults(func=cmd_shard)

    sub.add_parser(
        "serve",
        help="serve scene packages over gRPC: the fmgs-server command (needs fmgs[server]); "
        "`fmgs serve --help` lists its flags",
        add_help=False,
    )
    return p


def serve(argv: list[str]) -> int:
    """``fmgs serve ARGS`` execs ``fmgs-server ARGS`` (same process id): the core never imports the server."""
    import importlib.util
    import os

    if importlib.util.find_spec("fmgs_server") is None or importlib.util.find_spec("grpc") is None:
        print(
            "fmgs serve: the server is not installed: pip install 'fmgs[server]' (then run fmgs-server)",
            file=sys.stderr,
        )
        return 2
    sys.stdout.flush()
    os.execv(sys.executable, [sys.executable, "-m", "fmgs_server.cli", *argv])
    return 0  # pragma: no cover - exec does not return


def _auto_device() -> str:
    """``--device auto``: the first CUDA device when torch sees one, else the CPU."""
    import importlib.util

    if importlib.util.find_spec("torch") is None:
        return "cpu"
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["serve"]:
        return serve(argv[1:])
    args = build_parser().parse_args(argv)
    try:
        from fmgs.errors import FmgsError

        if getattr(args, "device", None) == "auto":
            args.device = _auto_device()
        try:
            return args.func(args)
        except FmgsError as e:
            print(f"fmgs: error: {e}", file=sys.stderr)
            return 2
    except ModuleNotFoundError as e:
        if e.name not in _CORE_MODULES:
            raise
        print(
            f"fmgs: `fmgs {args.command}` needs the core library ({e.name} is missing): "
            "pip install 'fmgs[core]' (the client-only install has fmgs-client)",
            file=sys.stderr,
        )
        return 2


_CORE_MODULES = ("torch", "numba", "safetensors", "plyfile", "scipy", "PIL", "tqdm")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
