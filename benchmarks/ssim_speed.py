"""SSIM forward + backward on CPU: the separable blur (fmgs.metrics.ssim) beside the full-window twin.

    python -m benchmarks.ssim_speed                  # 128x96x3 and 1920x1080x3, median of 5 runs
    python -m benchmarks.ssim_speed --threads 2 --runs 7

Both run in this one process on the same random float32 images, alternating run by run so load from
elsewhere on the machine falls on both alike. Prints a markdown table to stdout.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from collections.abc import Callable

import torch

from fmgs.metrics import ssim, ssim_reference

SIZES = ((128, 96), (1920, 1080))  # width x height


def _once(fn: Callable[..., torch.Tensor], img: torch.Tensor, ref: torch.Tensor) -> float:
    x = img.clone().requires_grad_()
    t0 = time.perf_counter()
    fn(x, ref).backward()
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5, help="timed runs per implementation and size")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (1: no oversubscription)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    gen = torch.Generator().manual_seed(0)
    print(
        f"CPU: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"{args.threads} thread(s), median of {args.runs} runs (1 warm-up), forward + backward, float32\n"
    )
    print("| image | full 11x11 window (ms) | separable (ms) | speed-up | |difference| of values |")
    print("|---|---:|---:|---:|---:|")
    for w, h in SIZES:
        img = torch.rand(h, w, 3, generator=gen)
        ref = torch.rand(h, w, 3, generator=gen)
        times: dict[str, list[float]] = {"full": [], "sep": []}
        for i in range(args.runs + 1):
            for name, fn in (("full", ssim_reference), ("sep", ssim)):
                t = _once(fn, img, ref)
                if i:  # the first pass warms allocators and kernels
                    times[name].append(t)
        full, sep = (statistics.median(times[k]) * 1e3 for k in ("full", "sep"))
        diff = abs(float(ssim(img, ref)) - float(ssim_reference(img, ref)))
        print(f"| {w}x{h}x3 | {full:.1f} | {sep:.1f} | {full / sep:.1f}x | {diff:.1e} |", flush=True)


if __name__ == "__main__":
    main()
