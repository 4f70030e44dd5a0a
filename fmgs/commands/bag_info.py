"""``fmgs bag-info``: what a robot's ROS 2 recording holds (topics, cameras, depth, tf frames), before
building from it."""

from __future__ import annotations

import argparse
import dataclasses
import json


def add_parser(sub) -> None:
    b = sub.add_parser(
        "bag-info",
        help="list a ROS 2 recording's topics, cameras, depth topics and tf frames (what `fmgs build` "
        "would pick from it)",
    )
    b.add_argument("recording", help="bag folder (metadata.yaml), .mcap or .db3 file")
    b.add_argument("--json", action="store_true", help="one JSON object instead of lines")
    b.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Print the recording's topics (types, counts), its colour and depth cameras and tf frames."""
    from fmgs.data.rosbag import recording_info

    info = recording_info(args.recording)
    if args.json:
        print(json.dumps(dataclasses.asdict(info)))
    else:
        print("\n".join(info.lines()))
    return 0
