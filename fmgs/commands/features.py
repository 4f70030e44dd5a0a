"""``fmgs features``: feature targets of a posed dataset into a feature cache (here or on Ray)."""

from __future__ import annotations

import argparse
from pathlib import Path

from fmgs.commands.common import config_flag, out_folder, settings, undistort_flag

TARGET_ALIASES = {"kind": "--targets"}
"""The short name the command has always had for TargetSpec.kind."""


def add_parser(sub) -> None:
    from fmgs import flags
    from fmgs.build.config import TargetSpec

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
    undistort_flag(fe)
    config_flag(fe, "target")
    flags.add_flags(fe.add_argument_group("targets (TargetSpec)"), TargetSpec, aliases=TARGET_ALIASES)
    fe.set_defaults(func=run)


def target_spec(args: argparse.Namespace):
    """TargetSpec from the flags and the --config file."""
    from fmgs.build.config import TargetSpec

    return settings(args, TargetSpec)


def run(args: argparse.Namespace) -> int:
    """Extract feature targets (hybrid CLIP + DINO, or label masks) of a posed dataset into a cache."""
    from fmgs.build import extract_features
    from fmgs.build.pipeline import model_revisions, resolve_build_models
    from fmgs.data.dataset import load_dataset

    spec = target_spec(args)
    out_folder(args.out, "the feature cache")
    revisions = model_revisions(spec, resolve_build_models(spec))  # every model, before any image
    if args.ray is not None:
        from fmgs.features.distributed import TargetJob, extract_features_ray

        pinned = tuple(sorted(revisions.items()))
        job = TargetJob(str(args.data), spec, args.device, args.undistort_dir, revisions=pinned)
        cache = extract_features_ray(job, Path(args.out), None if args.ray == "local" else args.ray)
    else:
        ds = load_dataset(args.data, undistort_dir=args.undistort_dir)
        cache = extract_features(ds, Path(args.out), spec, args.device, revisions=revisions)
    t = {k: f"{v.encoder} ({v.dim}-D)" for k, v in cache.targets.items()}
    print(f"feature cache {args.out}: {len(cache.image_names)} images, targets {t}")
    return 0
