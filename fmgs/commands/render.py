"""``fmgs render``: one camera of a dataset (or of a camera-path transforms.json) to a PNG."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from fmgs.commands.common import load_scene, positive_scale, undistort_flag


def add_parser(sub) -> None:
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
    undistort_flag(r)
    r.add_argument("--scale", type=float, default=1.0, help="resize the image by this factor")
    r.add_argument("--backend", default="auto", choices=["auto", "reference", "cpu", "cuda"])
    r.add_argument("--out", default="render.png")
    r.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Render one camera of a dataset (any layout fmgs reads, undistorted like training) to a PNG."""
    import numpy as np
    import torch
    from PIL import Image

    from fmgs.errors import ValidationError
    from fmgs.io.atomic import atomic_path
    from fmgs.render.rgb import render_rgb

    positive_scale("--scale", args.scale)
    fmt = image_format(args.out)
    g = load_scene(Path(args.scene))
    cam = render_camera(args).scaled(args.scale)
    t0 = time.perf_counter()
    with torch.no_grad():
        out = render_rgb(g, cam, background=torch.zeros(3), backend=args.backend)
    dt = time.perf_counter() - t0
    img = (out.image.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    try:  # a whole image or none: an interrupted or failed write leaves what was at --out
        with atomic_path(args.out) as tmp:
            Image.fromarray(img).save(tmp, format=fmt)
    except OSError as e:
        raise ValidationError("--out", f"cannot write {args.out} ({e})") from e
    print(
        f"wrote {args.out} ({cam.name}, {cam.width}x{cam.height}, {dt * 1000:.1f} ms, backend {args.backend})"
    )
    return 0


def image_format(out: str) -> str:
    """The PIL format of ``--out`` from its extension (.png, .jpg, ...); ValidationError for a folder
    or an extension no image format has."""
    from PIL import Image

    from fmgs.errors import ValidationError

    if Path(out).is_dir():
        raise ValidationError("--out", f"{out} is a folder: name the image file (e.g. render.png)")
    Image.init()
    fmt = Image.registered_extensions().get(Path(out).suffix.lower())
    if fmt is None or fmt not in Image.SAVE:
        raise ValidationError(
            "--out", f"{out}: not an image file name (its extension names no image format; use .png)"
        )
    return fmt


def render_camera(args: argparse.Namespace):
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
