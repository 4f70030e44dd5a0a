"""Certified top-K: exact answers from approximate scores that carry error bounds.

Every embedded Gaussian i has a served margin m_i = f_i.q - max_n f_i.c_n, computed in float64 from the
stored embedding (the "exact" score). A compact state gives, for every row, bounds lo_i <= m_i <= hi_i
at a fraction of the cost. The answer is the exact top K by (margin descending, row ascending) among
rows with margin >= m_min, found by rescoring exactly only the rows whose upper bound reaches the
current K-th exact margin:

1. rescore the ``first`` rows of highest upper bound; L = max(m_min, K-th exact margin among them);
2. rescore every other row whose upper bound is >= L; when there are many, first bound them more tightly
   and cheaply (``refine``: a float32 pass over the stored rows), raise L with the refined lower bounds,
   and rescore exactly only the rows whose refined upper bound still reaches it. Tiers of bounds chain
   (``certify_narrow``): each raises L and leaves only the rows its upper bounds cannot exclude.

Any row left unscored has hi_i < L <= the final K-th margin (more rows can only raise it), so it can
neither enter the answer nor tie with its last row: the answer is exact for any query. How many rows
were rescored is reported with it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch

from fmgs.query import tuning

ExactScorer = Callable[[torch.Tensor], torch.Tensor]
"""rows [k] int64 (sorted, unique) -> [k] float64 exact margins."""
Refiner = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
"""rows [k] int64 (sorted, unique) -> ([k] lower, [k] upper) float64 tighter bounds, cheaper than exact."""


class Refined(NamedTuple):
    """Tighter bounds over a sorted superset of a Pending's rows2 (one pass shared by several texts)."""

    rows: torch.Tensor
    """[U] int64 sorted, unique rows: every row of rows2, maybe others."""
    lower: torch.Tensor
    """[U] float64 lower bounds of their margins."""
    upper: torch.Tensor
    """[U] float64 upper bounds."""


class Certified(NamedTuple):
    """The exact top rows of one query."""

    rows: torch.Tensor
    """[K'] int64 rows, best first (K' <= K: fewer when the threshold leaves fewer)."""
    margin: torch.Tensor
    """[K'] float64 exact margins."""
    rescored: int
    """Rows whose exact margin was computed to certify the answer."""


def kth_largest(x: torch.Tensor, k: int) -> float:
    """The k-th largest value of x [n] (-inf when n < k)."""
    if k <= 0 or len(x) < k:
        return -math.inf
    return float(torch.topk(x, k, sorted=False).values.min())


def rows_at_least(x: torch.Tensor, cut: float) -> torch.Tensor:
    """Sorted rows [n] int64 of x [M] (CPU) with x >= cut. Contiguous float32 goes through a vector
    kernel (kernels.at_least, faster than numpy's compare and flatnonzero and than torch's:
    benchmarks/results/TUNING.md), which matters about twice per text; anything else through numpy."""
    a = x.numpy()
    if a.dtype != np.float32 or not a.flags.c_contiguous or a.ndim != 1:
        return torch.from_numpy(np.flatnonzero(a >= np.float64(cut)))  # not rounded to a's type
    from fmgs.query.kernels import LANES, at_least

    c = np.float32(cut)
    if float(c) < cut:  # the least float32 >= cut: float32 values reach it exactly when they reach cut
        c = np.nextafter(c, np.float32(np.inf))
    out = np.empty(tuning.SELECT_ROOM + LANES, np.int64)
    m = at_least(a, c, out)
    if m < 0:  # more rows than the buffer holds: numpy counts them, then writes them
        return torch.from_numpy(np.flatnonzero(a >= c))
    return torch.from_numpy(out[:m])


def _drop_sorted(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Sorted unique rows a [n] without those in sorted unique b [m]: b located in a (m log n), not a
    sort of both."""
    if len(a) == 0 or len(b) == 0:
        return a
    pos = torch.searchsorted(a, b).clamp_max(len(a) - 1)
    hit = pos[a[pos] == b]
    if len(hit) == 0:
        return a
    keep = torch.ones(len(a), dtype=torch.bool)
    keep[hit] = False
    return a[keep]


def _keep_sorted(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Rows of sorted unique a [n] that are also in sorted unique b [m] (a located in b)."""
    if len(a) == 0 or len(b) == 0:
        return a[:0]
    pos = torch.searchsorted(b, a).clamp_max(len(b) - 1)
    return a[b[pos] == a]


def top_rows(x: torch.Tensor, n: int) -> torch.Tensor:
    """Sorted indices [n] of n largest values of x [M] (which of several equal values at the cut is taken
    is unspecified, as for torch.topk, its twin). A cut from a strided sample (twice the share of n it
    should hold) leaves a few thousand candidates to select from: one pass over x, not a full top-n
    selection (benchmarks/results/TUNING.md)."""
    n = min(int(n), len(x))
    found = _candidates(x, n)
    if found is None:
        return torch.topk(x, n, sorted=False).indices.sort().values
    cand, values, _ = found
    return cand[torch.from_numpy(_top_mask(values, n))]


def _candidates(
    x: torch.Tensor, n: int, hint: float | None = None
) -> tuple[torch.Tensor, np.ndarray, float] | None:
    """(rows, values, cut): every row of x [M] with x >= cut, sorted, and their values (numpy), when there
    are at least n of them. The cut is ``hint`` when it leaves enough, else from a strided sample; None
    when neither does (then select over every value)."""
    if hint is not None:
        cand = rows_at_least(x, hint)
        if len(cand) >= n:
            return cand, x.numpy()[cand.numpy()], hint
    step = tuning.TOP_SAMPLE_STEP
    if len(x) >= 16 * step and 0 < n <= len(x) // 8:  # about 2n candidates: a saving
        s = x[::step]
        cut = float(torch.topk(s, min(len(s), 2 * -(-n // step) + 8), sorted=False).values.min())
        cand = rows_at_least(x, cut)
        if len(cand) >= n:  # else the sample misjudged the cut
            return cand, x.numpy()[cand.numpy()], cut
    return None


def _top_mask(values: np.ndarray, n: int) -> np.ndarray:
    """Mask [c] of the n largest of values [c] (no NaN; of several equal to the n-th, the first ones):
    a partition and two compares over the few thousand candidates, not a sort of them."""
    c = len(values)
    if n >= c:
        return np.ones(c, bool)
    if n <= 0:
        return np.zeros(c, bool)
    nth = np.partition(values, c - n)[c - n]
    mask = values > nth
    short = n - int(mask.sum())
    mask[np.flatnonzero(values == nth)[:short]] = True
    return mask


def order_rows(margin: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """Positions sorting by margin descending, ties by row ascending (reproducible)."""
    by_row = torch.argsort(rows)
    return by_row[torch.sort(margin[by_row], descending=True, stable=True).indices]


class Pending(NamedTuple):
    """A certification after its first step: the rows rescored, the bound L, the rows still to settle."""

    rows1: torch.Tensor
    """[n1] rows scored exactly."""
    m1: torch.Tensor
    """[n1] their exact margins."""
    bound: float
    """L, a lower bound on the k-th exact margin (or m_min): rows whose upper bound is below it are out."""
    rows2: torch.Tensor
    """[n2] int64 sorted rows whose upper bound reaches L, not yet scored."""

    @property
    def n2(self) -> int:
        """How many rows are still to settle."""
        return len(self.rows2)


def certify_start(
    upper: torch.Tensor,
    k: int,
    exact: ExactScorer,
    m_min: float = -math.inf,
    first: int = 0,
    hint: float | None = None,
) -> Pending:
    """Step 1: rescore the ``first`` rows of highest upper bound (at least k), find L and what remains.

    ``hint``: a cut estimated beforehand below both the first rows' bounds and L. One pass over the
    bounds then finds the rows reaching it, and both selections are made among them; when it misjudges
    (fewer rows than ``first``, or L below it) the steps fall back to their own passes. A speed choice:
    the answer is the same."""
    up = upper.detach().cpu()
    n1 = min(len(up), max(int(first), k))
    found = _candidates(up, n1, hint)
    if found is None:
        rows1 = torch.topk(up, n1, sorted=False).indices.sort().values
    else:
        cand, values, cut = found
        first_rows = _top_mask(values, n1)
        rows1 = cand[torch.from_numpy(first_rows)]
    m1 = exact(rows1)
    L = max(m_min, kth_largest(m1, k))
    if found is not None and L >= cut:  # every row reaching L is a candidate already: no second pass
        left = (values >= np.float64(L)) & ~first_rows  # float64: L is not rounded to the bounds' type
        return Pending(rows1, m1, L, cand[torch.from_numpy(left)])
    return Pending(rows1, m1, L, _drop_sorted(rows_at_least(up, L), rows1))


def _raise_bound(p: Pending, k: int, refined: Refined) -> tuple[float, torch.Tensor]:
    """L raised with a Refined superset's lower bounds, and the mask [U] of its rows still to settle
    (upper bound reaching L, not scored in step 1).

    A Refined superset may hold rows of step 1 (left out: they are scored already) and rows outside
    rows2, whose first upper bound was below p.bound: their lower bounds are below it too, so they cannot
    raise L, and any of them whose refined upper bound reaches L costs a little and changes nothing."""
    pos = torch.searchsorted(refined.rows, p.rows1)  # where step 1's rows sit, if they are there
    inside = pos < len(refined.rows)
    pos, r1 = pos[inside], p.rows1[inside]
    pos = pos[refined.rows[pos] == r1]
    # The k-th largest of step 1's margins and the other rows' lower bounds (k distinct rows reach it).
    # Lower bounds below p.bound cannot raise L: only the others are ranked (few, for a tight tier).
    high = refined.lower >= p.bound
    high[pos] = False
    L = max(p.bound, kth_largest(torch.cat([p.m1, refined.lower[high]]), k))
    keep = refined.upper >= L
    keep[pos] = False
    return L, keep


def certify_narrow(p: Pending, k: int, refined: Refined) -> Pending:
    """A tighter Pending from tighter bounds: L raised with their lower bounds, and only the rows of p.rows2
    whose refined upper bound still reaches L left (several tiers of bounds chain). ``refined`` may be a
    superset of p.rows2, or leave out rows of it whose refined upper bound is below p.bound (they are
    out, and their lower bounds cannot raise L)."""
    L, keep = _raise_bound(p, k, refined)
    return Pending(p.rows1, p.m1, L, _keep_sorted(refined.rows[keep], p.rows2))


def certify_finish(
    p: Pending,
    k: int,
    exact: ExactScorer,
    m_min: float = -math.inf,
    refined: tuple[torch.Tensor, torch.Tensor] | Refined | None = None,
) -> Certified:
    """Step 2: settle the remaining rows, optionally through tighter bounds: (lower, upper) of p.rows2,
    or a Refined superset of them (see ``_raise_bound``). L is raised with the lower bounds, then only
    rows whose upper bound still reaches it are rescored."""
    if isinstance(refined, Refined):
        L, keep = _raise_bound(p, k, refined)
        rows2 = refined.rows[keep]
    elif refined is not None:
        lo2, up2 = refined
        L = max(p.bound, kth_largest(torch.cat([p.m1, lo2]), k))  # k distinct rows reach these
        rows2 = p.rows2[up2 >= L]
    else:
        rows2 = p.rows2
    rows, margin = p.rows1, p.m1
    if len(rows2):
        rows, margin = torch.cat([p.rows1, rows2]), torch.cat([p.m1, exact(rows2)])
    keep = margin >= m_min
    rows, margin = rows[keep], margin[keep]
    top = order_rows(margin, rows)[:k]
    return Certified(rows[top], margin[top], len(p.rows1) + p.n2)


def certified_top_k(
    upper: torch.Tensor,
    k: int,
    exact: ExactScorer,
    m_min: float = -math.inf,
    first: int = 0,
    refine: Refiner | None = None,
    refine_above: int = 4096,
) -> Certified:
    """Exact top ``k`` rows by margin among rows with margin >= m_min (see the module docstring).

    upper [M] bounds every row's exact margin from above; ``exact`` computes it;
    ``refine`` (optional) bounds rows tightly, used when more than ``refine_above`` rows remain.
    """
    k = max(0, min(int(k), len(upper)))
    if k == 0:
        return Certified(torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.float64), 0)
    p = certify_start(upper, k, exact, m_min, first)
    refined = refine(p.rows2) if refine is not None and p.n2 > refine_above else None
    return certify_finish(p, k, exact, m_min, refined)


def threshold_margin(threshold: float, relevancy: Callable[[torch.Tensor], torch.Tensor]) -> float:
    """A margin below which ``relevancy`` (float32 margins -> float32 relevancy, non-decreasing) stays
    under ``threshold``: rows below it cannot pass the threshold test as served (-inf for threshold <= 0).

    Found by bisection on the served function itself, so float32 rounding near 0 or 1 cannot drop a row
    that passes.
    """
    if threshold <= 0:
        return -math.inf

    def passes(m: float) -> bool:
        return bool(relevancy(torch.tensor([m], dtype=torch.float32))[0] >= threshold)

    lo, hi = -1.0, 1.0
    while passes(lo) and lo > -1e6:
        lo *= 2
    if passes(lo):
        return -math.inf
    while not passes(hi):
        if hi > 1e6:
            return math.inf  # nothing passes (threshold above the largest relevancy)
        hi *= 2
    for _ in range(80):  # lo fails, hi passes
        mid = (lo + hi) / 2
        if mid in (lo, hi):
            break
        lo, hi = (lo, mid) if passes(mid) else (mid, hi)
    return lo  # every passing margin m has float32(m) > float32(lo), so m > lo
