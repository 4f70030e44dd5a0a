"""``fmgs synth``: render a synthetic labelled scene (Open3D ray casting) as a transforms.json dataset."""

from __future__ import annotations

import argparse
import time

from fmgs.commands.common import numbers


def add_parser(sub) -> None:
    from fmgs.synth import BACKDROPS, PRESETS, RIGS

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
    sy.add_argument(
        "--robot-bag",
        type=float,
        metavar="SECONDS",
        help="instead of the rig: a robot's ROS 2 recording of the scene (fmgs.synthbag), OUT/bag, a base "
        "driving once around it in this many seconds (images at 15 Hz, tf at 50 Hz, registered depth), "
        "with its true poses (truth.json), label images and scene.json beside it, for `fmgs build OUT/bag`",
    )
    sy.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Render a synthetic labelled scene (Open3D ray casting) as a transforms.json dataset."""
    from pathlib import Path

    from fmgs.errors import ValidationError
    from fmgs.synth import SynthConfig, generate

    w, h = image_size(args.size)
    if Path(args.out).exists() and not Path(args.out).is_dir():
        raise ValidationError("--out", f"{args.out} is a file, not a folder")
    dist = numbers("--distortion", args.distortion, 4, "four numbers k1,k2,p1,p2")
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
    if args.robot_bag is not None:
        from dataclasses import replace

        from fmgs.synthbag import RobotPathConfig, write_robot_bag

        if args.robot_bag <= 0:
            raise ValidationError("--robot-bag", "the drive's length in seconds must be positive")
        bag = write_robot_bag(args.out, RobotPathConfig(synth=replace(cfg, views=0), seconds=args.robot_bag))
        print(f"wrote {bag} ({args.robot_bag:g} s drive, {w}x{h}, {cfg.objects} objects) in "
              f"{time.perf_counter() - t0:.1f} s")  # fmt: skip
        return 0
    path = generate(args.out, cfg)
    secs = time.perf_counter() - t0
    print(f"wrote {path} ({cfg.views} views, {w}x{h}, {cfg.objects} objects) in {secs:.1f} s")
    return 0


def image_size(text: str) -> tuple[int, int]:
    """``--size WxH``: two whole numbers of pixels, each at least 1; ValidationError naming the flag."""
    from fmgs.errors import ValidationError

    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdecimal() for p in parts) or min(map(int, parts)) < 1:
        raise ValidationError(
            "--size", f"expected WxH in whole pixels (each at least 1, e.g. 128x96), got {text!r}"
        )
    return int(parts[0]), int(parts[1])
