"""What the GPU benchmark parts share: the device they run on, synchronised timing, peak memory and error
measures (benchmarks/gpu_parts.py, benchmarks/gpu_grpc.py)."""

from __future__ import annotations

import os
import time

import torch

DEVICE = os.environ.get("FMGS_BENCH_DEVICE", "cuda")
"""Where the parts run; "cpu" only to check the script itself on a machine without a GPU (--quick)."""
FAST = "cuda" if DEVICE == "cuda" else "cpu"
"""The fast rasteriser backend on DEVICE (gsplat on CUDA)."""

PAPER_FPS = 103.4
"""FMGS paper: 480x270 CLIP+DINO+RGB render on an RTX A5000."""
PAPER_FIELD_HOURS = 1.4
"""FMGS paper: 4.2K field steps on the A5000."""


def sync() -> None:
    if DEVICE == "cuda":
        torch.cuda.synchronize()


def peak_gib() -> float:
    """Peak device memory allocated by torch since the last reset (0 off CUDA)."""
    return torch.cuda.max_memory_allocated() / 2**30 if DEVICE == "cuda" else 0.0


def reset_peak() -> None:
    if DEVICE == "cuda":
        torch.cuda.reset_peak_memory_stats()


def timed(fn, runs: int, warm: int = 3) -> list[float]:
    """Seconds of each of ``runs`` calls of fn() after ``warm`` calls, the device synchronised around each."""
    for _ in range(warm):
        fn()
    sync()
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        sync()
        out.append(time.perf_counter() - t0)
    return out


def rel_max(a: torch.Tensor, b: torch.Tensor) -> float:
    """max |a-b| / max |b| in float64 (0 when both are zero)."""
    a, b = a.detach().double().cpu(), b.detach().double().cpu()
    den = float(b.abs().max()) if b.numel() else 0.0
    num = float((a - b).abs().max()) if b.numel() else 0.0
    return num / den if den > 0 else num


def rel_l2(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.detach().double().cpu(), b.detach().double().cpu()
    den = float(b.norm())
    return float((a - b).norm()) / den if den > 0 else float((a - b).norm())
