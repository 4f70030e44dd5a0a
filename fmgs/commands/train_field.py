"""``fmgs train-field``: distil a feature cache into the feature field over a frozen 3DGS scene."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from fmgs.commands.common import (
    AUTO_DEVICE,
    config_flag,
    load_scene,
    no_dotsim_flag,
    out_folder,
    settings,
    undistort_flag,
)

FIELD_ALIASES = {"steps": "--field-steps"}
"""The short name the command has always had for FieldTrainConfig.steps."""


def add_parser(sub) -> None:
    from fmgs import flags
    from fmgs.train.config import FieldTrainConfig

    tf = sub.add_parser("train-field", help="distil a feature cache into the feature field")
    tf.add_argument("data", help="posed dataset folder")
    tf.add_argument("--gaussians", required=True, help="frozen 3DGS scene (.ply, .splat or .safetensors)")
    tf.add_argument("--features", required=True, help="feature cache folder")
    tf.add_argument("--out", required=True, help="folder for the checkpoint and field_train.json")
    tf.add_argument("--package", help="also write a scene package to this folder (e.g. models/NAME)")
    undistort_flag(tf)
    _package_flags(tf)
    tf.add_argument("--restart", action="store_true", help="ignore an existing checkpoint in --out")
    config_flag(tf, "distillation")
    g = tf.add_argument_group("distillation (FieldTrainConfig; fewer --field-steps compress the schedule)")
    flags.add_flags(g, FieldTrainConfig, aliases=FIELD_ALIASES, defaults=AUTO_DEVICE)
    no_dotsim_flag(g)
    tf.set_defaults(func=run)


def _package_flags(p: argparse.ArgumentParser) -> None:
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


def field_config(args: argparse.Namespace):
    """FieldTrainConfig from the flags and the --config file."""
    from fmgs.train.config import FieldTrainConfig

    # Fewer steps compress the schedule (dotsim starts at the same fraction).
    cfg = settings(args, FieldTrainConfig, AUTO_DEVICE, lambda c: FieldTrainConfig().reduced(c.steps))
    return replace(cfg, dotsim_weight=0.0) if args.no_dotsim else cfg


def run(args: argparse.Namespace) -> int:
    """Distil a feature cache into the field over a frozen 3DGS scene; optionally write a package."""
    from fmgs.build import package_from_field
    from fmgs.data.dataset import load_dataset
    from fmgs.features.cache import FeatureCache
    from fmgs.features.text import load_text_encoder
    from fmgs.train.field import train_field

    out_folder(args.out, "the checkpoint and field_train.json")
    ds = load_dataset(args.data, undistort_dir=args.undistort_dir)
    g = load_scene(Path(args.gaussians))
    cache = FeatureCache.open(args.features)
    res = train_field(g, ds, cache, args.out, field_config(args), resume=not args.restart)
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
