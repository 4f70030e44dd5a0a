"""``fmgs train-gs``: 3D Gaussian Splatting on a posed dataset, written as point_cloud.ply."""

from __future__ import annotations

import argparse
from pathlib import Path

from fmgs.commands.common import AUTO_DEVICE, config_flag, out_folder, settings, undistort_flag

GS_ALIASES = {"image_scale": "--scale", "densify.grad_threshold": "--grad-threshold"}
"""The short names the command has always had for two GSTrainConfig fields."""


def add_parser(sub) -> None:
    from fmgs import flags
    from fmgs.train.config import GSTrainConfig

    t = sub.add_parser("train-gs", help="train 3D Gaussian Splatting on a posed dataset")
    t.add_argument("data", help="dataset folder (transforms.json or COLMAP sparse/0 + images/)")
    t.add_argument("--out", required=True)
    undistort_flag(t)
    t.add_argument("--restart", action="store_true", help="ignore an existing checkpoint in --out")
    config_flag(t, "training")
    g = t.add_argument_group("training (GSTrainConfig; fewer --steps compress the SH and densify schedule)")
    flags.add_flags(g, GSTrainConfig, aliases=GS_ALIASES, defaults=AUTO_DEVICE)
    t.set_defaults(func=run)


def gs_config(args: argparse.Namespace):
    """GSTrainConfig from the flags and the --config file."""
    from fmgs.train.config import GSTrainConfig

    # Fewer steps compress the SH and densification schedule (reduced() is the default at 30,000).
    return settings(args, GSTrainConfig, AUTO_DEVICE, lambda c: GSTrainConfig.reduced(c.steps))


def run(args: argparse.Namespace) -> int:
    """Train 3D Gaussian Splatting on a posed dataset and write point_cloud.ply."""
    from fmgs.data.dataset import load_dataset
    from fmgs.train.gaussians import train_gaussians

    cfg = gs_config(args)
    out_folder(args.out, "the checkpoint and point_cloud.ply")
    ds = load_dataset(args.data, undistort_dir=args.undistort_dir)
    res = train_gaussians(ds, args.out, cfg, resume=not args.restart)
    print(
        f"trained {res.steps} steps in {res.seconds:.0f} s: {res.gaussians.num} Gaussians, "
        f"final loss {res.final_loss:.4f}; wrote {Path(args.out) / 'point_cloud.ply'}"
    )
    return 0
