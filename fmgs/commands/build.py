"""``fmgs build``: photos (or a posed dataset, or a .ply with its posed images) to a scene package."""

from __future__ import annotations

import argparse
import json
import os
from dataclasses import replace
from pathlib import Path

from fmgs.commands.common import AUTO_DEVICE, config_flag, no_dotsim_flag, settings

# Settings of each stage come from its config dataclass: every field is a flag (fmgs/flags.py) and a key
# of the --config TOML file; the aliases keep the short names the commands have always had.
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
            "crop_scales",
            "crop_stride",
            "scale_blend",
            "segmenter",
            "segment_map",
            "labels",
            "names",
            "text_encoder",
            "feature_scale",
            "feature_side",
        )
    },
    **{
        f"recording.{k}": "--" + k.replace("_", "-")
        for k in ("image_topic", "camera_info_topic", "depth_topic", "fixed_frame")
    },
    "field.per_gaussian": "--per-gaussian",
    "field.adaptive_resolution": "--adaptive-resolution",
    "field.seed": "--seed",
}
BUILD_STAGE_OWNED = ("gs.device", "field.device")
"""Set from the build's own ``device`` for every stage."""


def add_parser(sub) -> None:
    from fmgs import flags
    from fmgs.build.config import BuildConfig

    b = sub.add_parser("build", help="photos or a posed dataset -> scene package in models/")
    b.add_argument(
        "source",
        help="photo folder, posed dataset folder, or a robot's ROS 2 recording (bag folder, .mcap, .db3)",
    )
    b.add_argument(
        "--extra", dest="extra_file", help="JSON file with an object merged into the manifest's extra"
    )
    b.add_argument(
        "--offline",
        action="store_true",
        help="never download models: use local folders and the hub cache only (as HF_HUB_OFFLINE=1 does); "
        "every missing model is named, with the command that fetches it, before the first stage runs",
    )
    b.add_argument(
        "--allow-newer-model",
        action="store_true",
        help="take the models' current hub revisions even where an earlier run of this build (its work "
        "folder's models.json) used others; without it a rerun loads the revisions it started with",
    )
    config_flag(b, "build")
    g = b.add_argument_group(
        "build (BuildConfig: the gs-, targets- and field- groups are the stages' settings; fewer "
        "--gs-steps or --field-steps compress that stage's schedule)"
    )
    flags.add_flags(g, BuildConfig, aliases=BUILD_ALIASES, defaults=AUTO_DEVICE, skip=BUILD_STAGE_OWNED)
    no_dotsim_flag(g)
    b.set_defaults(func=run)


def build_config(args: argparse.Namespace):
    """BuildConfig from the flags, the --config file and --extra (fewer steps compress a stage)."""
    from fmgs.build.config import BuildConfig
    from fmgs.errors import ValidationError

    def base(c):  # fewer steps compress each stage's schedule
        return BuildConfig.scheduled(c.name, c.gs.steps, c.field.steps)

    cfg = settings(args, BuildConfig, AUTO_DEVICE, base)
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


def run(args: argparse.Namespace) -> int:
    """Photos (or a posed dataset, or a .ply with its posed images) to a scene package in models/."""
    from fmgs.build import build_scene

    cfg = build_config(args)
    offline = "fmgs build --offline" if args.offline else None
    if args.offline:  # read at each model load, here and in Ray workers started from this process
        os.environ["FMGS_OFFLINE"] = "1"
    out = build_scene(args.source, cfg, offline=offline, allow_newer_model=args.allow_newer_model)
    print(f"wrote scene package {out}")
    return 0
