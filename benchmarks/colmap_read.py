"""COLMAP model reading: fmgs's own parser beside pycolmap's (fmgs.data.colmap.read_model backends).

    python -m benchmarks.colmap_read             # snowmiku (text and binary) and a 300K-point model
    python -m benchmarks.colmap_read --runs 7 --points 100000

The large model is synthetic (random points, 3 cameras, 50 images, written with write_binary, so no
tracks). The two readers alternate run by run on the same files; prints a markdown table to stdout.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import ROOT
from fmgs.data.colmap import ColmapCamera, ColmapImage, ColmapModel, read_model, write_binary

SNOW = ROOT.parent / "shared" / "data" / "snowmiku_small" / "sparse" / "0"


def _synthetic(n_points: int, out: Path) -> Path:
    rng = np.random.default_rng(0)
    cams = {i: ColmapCamera(i, "PINHOLE", 640, 480, [500.0 + i, 501.0, 320.0, 240.0]) for i in (1, 2, 3)}
    images = {}
    for i in range(1, 51):
        q = rng.normal(size=4)
        images[i] = ColmapImage(i, q / np.linalg.norm(q), rng.normal(size=3), 1 + i % 3, f"img_{i:04d}.png")
    pts = rng.normal(size=(n_points, 3)) * 5
    cols = rng.integers(0, 256, (n_points, 3)).astype(np.uint8)
    write_binary(ColmapModel(cams, images, pts, cols), out)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5, help="timed runs per reader and model")
    ap.add_argument("--points", type=int, default=300_000, help="points in the synthetic model")
    ap.add_argument("--snow", type=Path, default=SNOW, help="a real text model (snowmiku_small)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        models = {}
        if args.snow.is_dir():
            models["snowmiku text"] = args.snow
            write_binary(read_model(args.snow), Path(tmp) / "snow")
            models["snowmiku binary"] = Path(tmp) / "snow"
        models[f"synthetic binary, {args.points:,} points"] = _synthetic(args.points, Path(tmp) / "synth")
        print(f"CPU: {platform.processor() or platform.machine()}, median of {args.runs} runs (1 warm-up)\n")
        print("| model | points | fmgs (ms) | pycolmap (ms) | pycolmap / fmgs |")
        print("|---|---:|---:|---:|---:|")
        for name, path in models.items():
            times: dict[str, list[float]] = {"fmgs": [], "pycolmap": []}
            for i in range(args.runs + 1):
                for backend in times:
                    t0 = time.perf_counter()
                    m = read_model(path, backend=backend)
                    if i:  # the first pass warms the page cache and imports pycolmap
                        times[backend].append(time.perf_counter() - t0)
            f, p = (statistics.median(times[k]) * 1e3 for k in ("fmgs", "pycolmap"))
            print(f"| {name} | {len(m.points):,} | {f:.0f} | {p:.0f} | {p / f:.2f} |", flush=True)


if __name__ == "__main__":
    main()
