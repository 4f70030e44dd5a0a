"""Measuring: points of a work-precision diagram, error measures, the exact-point check, interleaved timing,
thread counts, growth fits, this machine's rates and the cost models of the floors, figures in words."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import torch

from benchmarks.common import D

GPU_NOTE = "not measured (no GPU lent)"


# ---------------------------------------------------------------------------------------------------
# Measured points and the checks on them


@dataclass
class Point:
    """One setting of one knob in a work-precision diagram."""

    curve: str
    """The knob (one curve per knob)."""
    label: str
    """The setting."""
    time_ms: float
    """Median run time (training time for the training sections)."""
    errors: dict[str, float]
    """Error measures against the exact reference (0 = identical)."""
    exact: bool = False
    """The exact reference path, re-run and compared like every other setting."""
    default: bool = False
    """The setting the project uses by default."""
    info: dict[str, Any] = field(default_factory=dict)
    """Other measured figures (bytes per Gaussian, p90, sizes)."""


def overlap_error(rows: Sequence[int], ref_rows: Sequence[int], k: int) -> float:
    """1 - |top-k(rows) ∩ top-k(ref_rows)| / k (0 when the two top-k sets are the same)."""
    return 1.0 - len(set(list(rows)[:k]) & set(list(ref_rows)[:k])) / k


def sorted_relevancy_error(rel: torch.Tensor, ref_rel: torch.Tensor) -> float:
    """max_i |rel[i] - ref_rel[i]| over two lists sorted best first (1 when their lengths differ)."""
    if len(rel) != len(ref_rel):
        return 1.0
    if len(rel) == 0:
        return 0.0
    return float((rel.double() - ref_rel.double()).abs().max())


class ImageError(NamedTuple):
    """A relevancy image against the reference image."""

    max_abs: float
    mean_abs: float
    argmax_same: bool
    argmax_px: float
    """Distance in pixels between the two most relevant pixels."""


def image_error(rel: torch.Tensor, ref: torch.Tensor) -> ImageError:
    """Max and mean |rel - ref| over [H,W] pixels, whether the most relevant pixel is the same one and how
    far it moved."""
    d = (rel.double() - ref.double()).abs()
    a, b = divmod(int(torch.argmax(rel)), rel.shape[-1]), divmod(int(torch.argmax(ref)), ref.shape[-1])
    return ImageError(float(d.max()), float(d.mean()), a == b, math.dist(a, b))


def exact_failures(results: dict[str, dict]) -> list[str]:
    """'section/curve/label: errors' for every exact point with a non-zero error."""
    bad = []
    for name, sec in results.items():
        for p in sec.get("points", []):
            nonzero = {k: v for k, v in p["errors"].items() if v != 0}
            if p["exact"] and nonzero:
                bad.append(f"{name}/{p['curve']}/{p['label']}: {nonzero}")
    return bad


def interleaved(
    fns: dict[str, Callable[[int], Any]], n_inputs: int, reps: int = 1, warmup: int = 1
) -> tuple[dict[str, list[float]], dict[str, list[Any]]]:
    """Time every fn on inputs 0..n_inputs-1, ``reps`` passes, the order of fns rotated per input so all
    settings see the same machine load; returns seconds per call and the outputs of the last pass."""
    names = list(fns)
    times: dict[str, list[float]] = {n: [] for n in names}
    outs: dict[str, list[Any]] = {n: [None] * n_inputs for n in names}
    for _ in range(warmup):  # compiled kernels, caches, thread pools
        for n in names:
            fns[n](0)
    turn = 0
    for _ in range(reps):
        for i in range(n_inputs):
            for j in range(len(names)):
                n = names[(j + turn) % len(names)]
                t0 = time.perf_counter()
                outs[n][i] = fns[n](i)
                times[n].append(time.perf_counter() - t0)
            turn += 1
    return times, outs


# ---------------------------------------------------------------------------------------------------
# Threads


def set_threads(n: int) -> None:
    """torch and numba (this thread's parallel regions) use n threads."""
    import numba

    torch.set_num_threads(n)
    numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))


def with_threads(n: int, fn: Callable[[], Any]) -> Callable[[], Any]:
    def run():
        set_threads(n)
        return fn()

    return run


# ---------------------------------------------------------------------------------------------------
# Growth and floors


class Growth(NamedTuple):
    """How a time grows with a size."""

    exponent: float
    """Slope of log(time) against log(size) over the largest half of the sizes."""
    fixed_ms: float
    """Intercept of the linear fit time = fixed + per_unit * size (least relative squares)."""
    per_unit_ns: float
    """Slope of the linear fit, ns per unit of size."""
    rel_rms_linear: float
    """Relative RMS residual of the linear fit."""
    rel_rms_nlogn: float
    """Relative RMS residual of time = fixed + c * size * log2(size)."""
    model: str
    """'linear', 'n log n', 'sub-linear' or 'super-linear' (from the exponent and the residuals)."""
    linear_lo: float
    """Smallest size of the linear regime: the contiguous sizes around the cheapest time per unit whose
    time per unit stays within 25% of it (below: a fixed cost dominates)."""
    linear_hi: float
    """Largest size of the linear regime (above: the time per unit grows, e.g. out of cache)."""
    best_unit_ns: float
    """The cheapest time per unit measured (ns)."""
    top_unit_ns: float
    """Time per unit at the largest size (ns)."""


def _fit2(basis: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float]:
    """Least squares of relative residuals y ~ a + b*basis; returns (a, b) and the relative RMS."""
    A = np.stack([np.ones_like(basis), basis], 1) / y[:, None]
    coef, *_ = np.linalg.lstsq(A, np.ones_like(y), rcond=None)
    pred = coef[0] + coef[1] * basis
    return coef, float(np.sqrt(np.mean(((pred - y) / y) ** 2)))


def fit_growth(sizes: Sequence[float], times_ms: Sequence[float]) -> Growth:
    """Fit time against size (at least 2 sizes); see Growth."""
    x, y = np.asarray(sizes, np.float64), np.asarray(times_ms, np.float64)
    order = np.argsort(x)
    x, y = x[order], y[order]
    h = max(2, (len(x) + 1) // 2)
    lx, ly = np.log(x[-h:]), np.log(y[-h:])
    p = float(np.polyfit(lx, ly, 1)[0]) if len(lx) >= 2 else float("nan")
    (a, b), e_lin = _fit2(x, y)
    _, e_nlogn = _fit2(x * np.log2(np.maximum(x, 2)), y)
    unit = y / x
    best = int(np.argmin(unit))
    within = unit <= 1.25 * unit[best]
    lo = hi = best
    while lo > 0 and within[lo - 1]:
        lo -= 1
    while hi < len(x) - 1 and within[hi + 1]:
        hi += 1
    if p < 0.85:
        model = "sub-linear"
    elif p > 1.25:
        model = "super-linear"
    elif e_nlogn < 0.7 * e_lin and p > 1.05:
        model = "n log n"
    else:
        model = "linear"
    return Growth(
        p,
        float(a),
        float(b) * 1e6,
        e_lin,
        e_nlogn,
        model,
        float(x[lo]),
        float(x[hi]),
        unit[best] * 1e6,
        unit[-1] * 1e6,
    )


@dataclass(frozen=True)
class Rates:
    """This machine's measured limits."""

    bandwidth_gbs: float
    """Memory read bandwidth, GB/s (1e9 bytes)."""
    gflops: float
    """float32 arithmetic rate, GFLOP/s (dense matmul, all cores)."""


class Cost(NamedTuple):
    """Bytes that must move and arithmetic that must be done."""

    bytes: float
    flops: float


def floor_ms(cost: Cost, rates: Rates) -> float:
    """The time neither memory nor arithmetic can beat: max(bytes / bandwidth, flops / rate)."""
    return max(cost.bytes / (rates.bandwidth_gbs * 1e9), cost.flops / (rates.gflops * 1e9)) * 1e3


def text_query_cost(gaussians: int, rank: int, dim: int = D, rerank_rows: int = 0) -> Cost:
    """A compact scan: int8 coefficients (rank bytes) + the shift read, the score written and read back
    by top-k (3 float32 per Gaussian), 2*rank flops per Gaussian; plus the re-ranked rows (float16,
    dim values each, dotted with the query and 4 canonical vectors)."""
    return Cost(
        gaussians * (rank + 12) + rerank_rows * dim * 2,
        2.0 * gaussians * rank + rerank_rows * dim * 2 * 5,
    )


def exact_query_cost(gaussians: int, dim: int = D) -> Cost:
    """An exact float32 scan: every embedding read once (4*dim bytes), 2*dim flops per Gaussian."""
    return Cost(gaussians * (4 * dim + 12), 2.0 * gaussians * dim)


RENDER_FLOPS_PER_PAIR = 14
"""Per (pixel, contributing Gaussian): offset (2), conic power (6), exp (counted as 1), alpha clamp (1),
weight (1), transmittance update (2), alpha accumulation (1); plus 2 per channel for the blend."""
PROJECT_FLOPS = 150
"""Per Gaussian: rotation to a 3D covariance, the EWA Jacobian, the 2D conic and its radius."""


def render_cost(pairs: float, gaussians: int, pixels: int, channels: int) -> Cost:
    """Render model: every contributing (pixel, Gaussian) pair blended, every Gaussian projected once and
    its projected parameters and channels read once, the image (channels, alpha, depth) written once."""
    flops = pairs * (RENDER_FLOPS_PER_PAIR + 2 * channels) + gaussians * PROJECT_FLOPS
    nbytes = gaussians * (14 + channels) * 4 + pixels * (channels + 2) * 4
    return Cost(nbytes, flops)


def measure_rates(nbytes: int, n: int, reps: int) -> Rates:
    """Bandwidth: the best of ``reps`` sums of an nbytes float32 array; rate: the best of float32 n x n
    matmuls (both on all cores through torch)."""
    return Rates(nbytes / _best_sum(nbytes, reps) / 1e9, 2.0 * n**3 / _best_matmul(n, reps) / 1e9)


def _best_sum(nbytes: int, reps: int) -> float:
    arr = torch.ones(nbytes // 4)
    arr.sum()
    return min(timed(arr.sum) for _ in range(reps))


def _best_matmul(n: int, reps: int) -> float:
    x, y = torch.randn(n, n), torch.randn(n, n)
    x @ y
    return min(timed(lambda: x @ y) for _ in range(reps))


def timed(fn: Callable[[], Any]) -> float:
    """Seconds of one call."""
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


# ---------------------------------------------------------------------------------------------------
# Figures in words


def e(x: float) -> str:
    """An error: exactly 0 shown as 0."""
    return "0" if x == 0 else f"{x:.1e}"


def pct(x: float) -> str:
    return f"{100 * x:.1f}%"
