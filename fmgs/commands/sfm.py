"""``fmgs sfm``: photos to poses with pycolmap, then undistortion into a dataset folder."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from fmgs.commands.common import config_flag, out_folder, settings


def add_parser(sub) -> None:
    from fmgs import flags
    from fmgs.sfm.config import SfMConfig

    sf = sub.add_parser("sfm", help="photos to poses with pycolmap; writes OUT/undistorted (a dataset)")
    sf.add_argument("images", help="folder of photos")
    sf.add_argument("--out", required=True)
    sf.add_argument("--per-image-camera", action="store_true", help="one camera per photo (mixed devices)")
    config_flag(sf, "structure-from-motion")
    flags.add_flags(sf.add_argument_group("structure from motion (SfMConfig)"), SfMConfig)
    sf.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Photos to poses: pycolmap SfM, then undistortion into a dataset folder."""
    import logging

    from fmgs.sfm import run_sfm
    from fmgs.sfm.config import SfMConfig

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = settings(args, SfMConfig)
    out_folder(args.out, "the reconstruction")
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
