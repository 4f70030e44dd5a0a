"""``fmgs eval-gs``: PSNR and SSIM of a 3DGS scene on a dataset's held-out views."""

from __future__ import annotations

import argparse
from pathlib import Path

from fmgs.commands.common import load_scene, numbers, out_folder, positive_scale, undistort_flag


def add_parser(sub) -> None:
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
    undistort_flag(e)
    e.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """PSNR and SSIM of a 3DGS scene on the dataset's held-out views."""
    from fmgs.data.dataset import load_dataset
    from fmgs.errors import ValidationError
    from fmgs.train.evaluate import evaluate
    from fmgs.train.floaters import floater_mask
    from fmgs.train.gaussians import dataset_background, trained_background

    positive_scale("--scale", args.scale)
    if args.background != "auto":
        bg = numbers("--background", args.background, 3, "auto or R,G,B in [0,1]")
        if not all(0.0 <= v <= 1.0 for v in bg):  # NaN fails too
            raise ValidationError("--background", f"expected auto or R,G,B in [0,1], got {args.background!r}")
    out_folder(args.out, "eval.json and the renders")
    ds = load_dataset(args.data, undistort_dir=args.undistort_dir)
    g = load_scene(Path(args.scene))
    if args.out:
        try:
            (Path(args.out) / "renders").mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ValidationError("--out", f"cannot make {args.out} ({e})") from e
    if args.background == "auto":  # what the scene was trained with (its train.json), else the dataset's
        scene = Path(args.scene)
        bg = trained_background(scene.parent, ds) if scene.is_file() else dataset_background(ds)
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
