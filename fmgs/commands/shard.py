"""``fmgs shard``: split a scene package into spatial shards, each a package, with a shard manifest."""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path


def add_parser(sub) -> None:
    sh = sub.add_parser(
        "shard",
        help="split a scene package into K spatial shards (a balanced k-d split of the means) for serving "
        "a scene bigger than one node on a Ray cluster",
    )
    sh.add_argument("package", help="scene package folder, e.g. models/NAME")
    sh.add_argument("--shards", type=int, required=True, help="number of shards K (1..4096)")
    sh.add_argument("--out", help="folder for the sharded scene (default: PACKAGE-Kshards beside it)")
    sh.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Split a scene package into spatial shards (each a package) with a shard manifest."""
    from fmgs.scene.shards import ShardManifest, write_shards

    src = Path(args.package)
    here = Path(os.path.abspath(src))  # "." or "models/x/.." name a folder by its own name
    out = Path(args.out) if args.out else here.parent / f"{here.name}-{args.shards}shards"
    t0 = time.perf_counter()
    write_shards(src, out, args.shards)
    sm = ShardManifest.read(out)
    rows = [f"  {s.folder}: {s.num_gaussians} Gaussians, {s.num_selected} embedded" for s in sm.shards]
    print(f"{out}: {len(sm.shards)} shards of {sm.name} in {time.perf_counter() - t0:.1f} s", *rows, sep="\n")
    return 0
