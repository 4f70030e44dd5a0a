"""A text query's plan: the first pass each text takes over every row, the passes that narrow what it
leaves, and the certificate that settles the rest (fmgs.query.certify). Every choice here is a speed
choice: answers are exact whatever pass a text takes (fmgs.query.tuning holds the knobs).

For the texts of one request (queries q [n,D], top k):

1. ``choose_first_pass``: on the compact path with a second tier, a sample of the rows estimates how
   many rows the first tier's bounds would leave each text. Texts it settles (typical, near) take the
   first tier (r bytes a row); the others (CLIP-like, absent) take the first tier and the second tier's
   head, or the whole second tier, whichever is estimated cheaper. The sample also gives each text a
   hint, a cut for certify_start's selections.
2. ``first_pass_upper``: every row's upper bound for each text through the pass it takes.
3. certify_start: the ``first_rescore_count`` rows of highest bound are rescored exactly; their k-th
   margin is L, and the rows whose bound reaches L are left.
4. ``narrow_pending``: texts that did not take the whole second tier first and have more than
   REFINE_ABOVE rows left bound them through both tiers (certify_narrow).
5. ``refine_pending``: texts still above REFINE_ABOVE bound them by a float32 pass over their float16
   embeddings; certify_finish rescores in float64 what still reaches L.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple, Protocol

import numpy as np
import torch

from fmgs.query import tuning
from fmgs.query.certify import (
    Certified,
    Pending,
    Refined,
    certify_finish,
    certify_narrow,
    certify_start,
)

if TYPE_CHECKING:
    from fmgs.query.bounds import CompactBounds, HalfRows
    from fmgs.query.config import IndexConfig
    from fmgs.query.state import QueryState

EXACT_TABLE = "float32 table"
"""The exact path's first pass: one float32 product with every stored row."""
FIRST_TIER = "first tier"
"""The compact state's first tier over every row (r int8 codes a row)."""
FIRST_TIER_AND_HEAD = "first tier + head"
"""The first tier and the second tier's head over every row; the rows it leaves read the tail."""
SECOND_TIER = "second tier"
"""Both tiers whole over every row."""
NO_PASS = "none"
"""Nothing to rank (top_k 0 or an empty index)."""


class PlannedIndex(Protocol):
    """What the plan reads of an index: fmgs.query.index.EmbeddingIndex, which calls the plan with itself
    (a protocol, so this module does not import the index that imports it)."""

    state: QueryState | None
    """The compact state (None on the exact path)."""
    cfg: IndexConfig
    """The index's settings (``rerank``)."""
    compact: CompactBounds | None
    """Bounds from the compact state's tiers (None on the exact path)."""
    half_rows: HalfRows | None
    """The float16 kernels over the stored embeddings (None without them)."""
    canonical_max: torch.Tensor
    """[M] the largest stored canonical dot per row (float32)."""

    @property
    def exact(self) -> bool: ...

    @property
    def num(self) -> int: ...

    def upper_bounds(self, q: torch.Tensor, canonical_vectors: torch.Tensor | None = None) -> torch.Tensor:
        """[M,n] upper bounds on every row's margin from the cheap pass."""
        ...

    def exact_dots(self, rows: torch.Tensor, vectors: torch.Tensor) -> torch.Tensor:
        """[k,n] float64 f.v for rows [k] from the stored embeddings."""
        ...


class FirstPass(NamedTuple):
    """How each text of a request takes its pass over every row (``choose_first_pass``); texts in
    neither list take the first tier (or the float32 table on the exact path)."""

    direct: list[int]
    """Texts through the whole second tier."""
    head: list[int]
    """Texts through the first tier and the second tier's head."""
    hint: np.ndarray | None
    """[n] float64: each text's cut for certify_start (``hints``; None: not estimated)."""


class Explanation(NamedTuple):
    """How one text's answer was certified (``EmbeddingIndex.explain``)."""

    first_pass: str
    """The pass that bounded every row: EXACT_TABLE, FIRST_TIER, FIRST_TIER_AND_HEAD, SECOND_TIER (or
    NO_PASS)."""
    rows: int
    """Rows in the index."""
    first_rescored: int
    """Rows of highest bound rescored exactly first (``first_rescore_count``, at least k)."""
    left_by_first_pass: int
    """Other rows whose first-pass bound reached L, the k-th margin among those: still to settle."""
    left_by_second_tier: int | None
    """Of those, the rows the second tier's bounds left (None: not narrowed by it)."""
    left_by_refinement: int | None
    """Rows the float32 refinement left to float64 rescoring (None: not refined; it bounds a superset
    shared by the request's texts, so this may count a few rows outside the ones left)."""
    scored_exactly: int
    """Rows scored exactly in all: the first ones and what the last step left. (``Ranked.rescored`` is
    first_rescored plus the rows left after the second tier: it counts those refinement settled.)"""
    hinted: bool
    """Whether certify_start had a cut estimated from the sample (``hints``)."""


def first_rescore_count(index: PlannedIndex, k: int) -> int:
    """How many rows of highest bound certification rescores first for the top k: rerank * k, but at
    most REFINE_ABOVE beyond k (a large k would pay float64 rescoring for rows the refinement pass
    settles more cheaply); k on the exact path."""
    if index.state is None:
        return k
    return min(index.num, max(k, min(index.cfg.rerank * k, k + tuning.REFINE_ABOVE)))


def choose_first_pass(index: PlannedIndex, q: torch.Tensor, k: int, first: int) -> FirstPass:
    """Texts whose first-tier bound would leave more than TIER2_FIRST_FRACTION of the rows (CLIP-like
    and absent queries): the head's take their first pass through the first tier and the second tier's
    head when that is estimated to leave at most HEAD_FRACTION of the rows (and no more than HEAD_TEXTS
    texts leave the first tier), the direct ones through the whole second tier over every row. Estimated
    on every TIER2_FIRST_STEP-th row: each pass's upper bounds against the sample's best second-tier
    lower bounds. Also each text's hint for certify_start (``hints``); ``first``: the rows rescored
    first (``first_rescore_count``). Speed decisions only: every pass gives exact answers."""
    b = index.compact
    if b is None or not b.estimates_first_pass:
        return FirstPass([], [], None)
    s = b.sample
    n_s = len(s.shift)
    lo2, up2 = b.tier2_bounds(torch.arange(n_s), q, tables=s)
    up1 = b.sample_first_tier_upper(q)  # [n,S]
    ks = max(1, -(-k // tuning.TIER2_FIRST_STEP))
    best = torch.topk(lo2, min(tuning.HINT_BELOW * ks + 1, n_s), dim=1).values
    L = best[:, min(ks, n_s) - 1, None]  # [n,1]: the sample's ks-th best lower bound
    frac = (up1.double() >= L).double().mean(1)
    second = [j for j in range(len(q)) if float(frac[j]) > tuning.TIER2_FIRST_FRACTION]
    est = up1.double()  # each text's sample bounds from the pass it will take
    head = []
    if second and b.has_head and len(second) <= tuning.HEAD_TEXTS:
        up15 = b.tier2_upper(q[second], empty32(len(second), n_s), tables=s, head=True).double()
        frac15 = (up15 >= L[second]).double().mean(1)
        head = [j for c, j in enumerate(second) if float(frac15[c]) <= tuning.HEAD_FRACTION]
        est[head] = up15[[second.index(j) for j in head]]
    direct = [j for j in second if j not in head]
    est[direct] = up2[direct]
    return FirstPass(direct, head, hints(est, best[:, -1], first, index.num))


def hints(est: torch.Tensor, low: torch.Tensor, first: int, num: int) -> np.ndarray:
    """Each text's hint [n] for certify_start (float32 values as float64), from its sample's upper
    bounds est [n,S] (of the pass it takes) and low [n], the sample's (HINT_BELOW ks + 1)-th best lower
    bound: low enough that the ``first`` rows of highest bound (of ``num``) reach it (twice their share
    of the sample, as certify.top_rows estimates), and that, most often, so does every row reaching the
    k-th exact margin (benchmarks/results/TUNING.md)."""
    n_s = est.shape[1]
    take = min(n_s, 2 * -(-first * n_s // num) + 8)
    top = torch.topk(est, take, dim=1).values[:, -1]
    return torch.minimum(top, low).float().double().numpy()


def first_pass_upper(
    index: PlannedIndex, q: torch.Tensor, cv: torch.Tensor | None, fp: FirstPass
) -> torch.Tensor:
    """[n,M] upper bounds on every row's margin: ``index.upper_bounds`` (the first tier, or the float32
    table), or for the texts in ``fp.direct`` the whole second tier's, for those in ``fp.head`` the first
    tier's and the second's head (both rounded up to float32)."""
    n, M = len(q), index.num
    rest = [j for j in range(n) if j not in fp.direct and j not in fp.head]
    if len(rest) == n:
        return index.upper_bounds(q, cv).T.contiguous()
    b = index.compact
    passes = [(fp.direct, b.tier2_upper), (fp.head, lambda v, out: b.tier2_upper(v, out, head=True))]
    out = empty32(n, M)
    if rest:
        out[rest] = index.upper_bounds(q[rest], cv).T
    for texts, run in passes:
        if len(texts) == n:
            return run(q, out)
        if texts:
            out[texts] = run(q[texts], empty32(len(texts), M))
    return out


def narrow_pending(
    index: PlannedIndex, pending: list[Pending], q: torch.Tensor, k: int, skip: list[int] = ()
) -> list[Pending]:
    """The texts with more than REFINE_ABOVE rows left, narrowed by the second tier's bounds (one pass
    over the union of their rows for all of them); the others (and those in ``skip``) as they are.

    The pass runs REFINE_CHUNK rows at a time into reused buffers and keeps, per text, only the rows
    whose second-tier upper bound reaches that text's L: the others are out whatever L becomes (it
    only rises), and their lower bounds, below L, cannot raise it."""
    big = [j for j, p in enumerate(pending) if p.n2 > tuning.REFINE_ABOVE and j not in skip]
    b = index.compact
    if b is None or b.tier2 is None or not big:
        return pending
    union = union_rows(pending, big, index.num)
    qb = q[big]
    chunk = tuning.REFINE_CHUNK
    size = min(chunk, len(union))
    buf = (
        torch.empty(len(big), size, dtype=torch.float64),
        torch.empty(len(big), size, dtype=torch.float64),
    )
    kept: list[list[tuple[torch.Tensor, ...]]] = [[] for _ in big]
    for s in range(0, len(union), chunk):
        part = union[s : s + chunk]
        lo, up = (x[:, : len(part)] for x in buf)
        b.tier2_bounds(part, qb, into=(lo, up))
        for c, j in enumerate(big):
            sel = torch.nonzero(up[c] >= pending[j].bound).reshape(-1)
            kept[c].append((part[sel], lo[c, sel], up[c, sel]))
    out = list(pending)
    for c, j in enumerate(big):
        rows, lo, up = (torch.cat(x) for x in zip(*kept[c], strict=True))
        out[j] = certify_narrow(pending[j], k, Refined(rows, lo, up))
    return out


def refine_pending(
    index: PlannedIndex, pending: list[Pending], q: torch.Tensor, cv: torch.Tensor | None
) -> dict[int, Refined]:
    """Tighter bounds for the texts with more than REFINE_ABOVE rows left: one float32 pass over the
    union of those rows for all of them at once. Returns {text: Refined} over the union (a sorted
    superset of each text's rows2: certify_finish reads it as it is, no per-text gathering)."""
    big = [j for j, p in enumerate(pending) if p.n2 > tuning.REFINE_ABOVE]
    if index.half_rows is None or not big:
        return {}
    union = union_rows(pending, big, index.num)
    lo = torch.empty(len(big), len(union), dtype=torch.float64)
    up = torch.empty_like(lo)
    chunk = tuning.REFINE_CHUNK
    for s in range(0, len(union), chunk):  # bounded working memory for the kernel's inputs
        part = union[s : s + chunk]
        index.half_rows.refine(part, q[big], cv, (lo[:, s : s + len(part)], up[:, s : s + len(part)]))
    return {j: Refined(union, lo[c], up[c]) for c, j in enumerate(big)}


def union_rows(pending: list[Pending], texts: list[int], num: int) -> torch.Tensor:
    """Sorted rows [U] still to settle for any of ``texts`` (of ``num`` rows): a sort of their lists when
    they are short, a mask over the rows when they hold a sizeable share of them (O(num))."""
    parts = [pending[j].rows2 for j in texts]
    total = sum(len(r) for r in parts)
    if len(parts) == 1:
        return parts[0]
    if total * 16 < num:
        return torch.unique(torch.cat(parts))
    member = np.zeros(num, bool)
    for r in parts:
        member[r.numpy()] = True
    return torch.from_numpy(np.flatnonzero(member))


def empty32(n: int, m: int) -> torch.Tensor:
    """An uninitialised float32 [n,m] from numpy's allocator, which asks for huge pages on large arrays
    where torch's large CPU allocations take fresh 4 KB pages (benchmarks/results/TUNING.md)."""
    return torch.from_numpy(np.empty((n, m), np.float32))


class Scorer:
    """A text's exact margins for rows (certify's ExactScorer), keeping the f.q it computed so the answer's
    similarities are not computed twice (10K float64 dots for k = 10,000)."""

    def __init__(self, index: PlannedIndex, vecs: torch.Tensor, cmax: torch.Tensor | None) -> None:
        """vecs [1+C,D]: the query, then custom canonical vectors; cmax [M]: the stored canonical maxima
        (float32, widened exactly to float64 per row; None when custom vectors are given)."""
        self.index, self.vecs, self.cmax = index, vecs, cmax
        self.rows: list[torch.Tensor] = []
        self.sims: list[torch.Tensor] = []

    def __call__(self, rows: torch.Tensor) -> torch.Tensor:
        d = self.index.exact_dots(rows, self.vecs).cpu()
        self.rows.append(rows.cpu())
        self.sims.append(d[:, 0])
        if self.cmax is not None:
            return d[:, 0] - self.cmax[rows.to(self.cmax.device)].cpu().double()
        return d[:, 0] - d[:, 1:].amax(1)

    @property
    def scored(self) -> int:
        """Rows scored so far."""
        return sum(len(r) for r in self.rows)

    def similarity(self, rows: torch.Tensor) -> torch.Tensor:
        """[k] float64 f.q of rows scored before."""
        if len(rows) == 0:
            return torch.zeros(0, dtype=torch.float64)
        seen, sims = torch.cat(self.rows), torch.cat(self.sims)
        order = torch.argsort(seen)
        pos = order[torch.searchsorted(seen[order], rows).clamp_max(len(seen) - 1)]
        if not torch.equal(seen[pos], rows):
            raise RuntimeError("a row of the answer was never scored exactly")  # certify's invariant
        return sims[pos]


def certify_texts(
    index: PlannedIndex,
    q: torch.Tensor,
    k: int,
    m_min: float,
    cv: torch.Tensor | None,
    between: Callable[[int], None] | None = None,
    explained: list[Explanation] | None = None,
) -> list[tuple[Certified, Scorer]]:
    """The certified top k (1 <= k <= rows) of each unit query q [n,D] (on the index's device) with
    margin >= m_min, and the scorer that holds its rows' similarities; cv [C,D]: custom canonical
    vectors (None: the stored maxima). ``between(j)`` runs before text j is certified (a deadline check
    may raise there); ``explained``: each text's Explanation is appended to it."""
    n = len(q)
    first = first_rescore_count(index, k)
    fp = choose_first_pass(index, q, k, first) if cv is None else FirstPass([], [], None)
    upper = first_pass_upper(index, q, cv, fp)  # [n,M]: each text's bounds in one run of memory
    # None: margins against the custom vectors. Float32 maxima, widened per scored row (a float64 copy
    # of all M would cost 80 MB of fresh pages per query at 10M Gaussians).
    stored = None if cv is not None else index.canonical_max
    scorers = [
        Scorer(index, q[j : j + 1] if cv is None else torch.cat([q[j : j + 1], cv]), stored) for j in range(n)
    ]
    pending = []
    for j in range(n):
        if between is not None:
            between(j)
        hint = None if fp.hint is None else float(fp.hint[j])
        pending.append(certify_start(upper[j], k, scorers[j], m_min, first, hint))
    started = pending
    if cv is None:
        pending = narrow_pending(index, pending, q, k, skip=fp.direct)
    refined = refine_pending(index, pending, q, cv)
    done = [
        (certify_finish(p, k, scorers[j], m_min, refined.get(j)), scorers[j]) for j, p in enumerate(pending)
    ]
    if explained is not None:
        for j in range(n):
            explained.append(_explain(index, fp, j, started[j], pending[j], j in refined, scorers[j]))
    return done


def _explain(
    index: PlannedIndex,
    fp: FirstPass,
    j: int,
    started: Pending,
    narrowed: Pending,
    refined: bool,
    scorer: Scorer,
) -> Explanation:
    """Text j's Explanation from its Pending after certify_start and after narrowing, and its scorer."""
    if j in fp.direct:
        first_pass = SECOND_TIER
    elif j in fp.head:
        first_pass = FIRST_TIER_AND_HEAD
    else:
        first_pass = EXACT_TABLE if index.exact else FIRST_TIER
    n1 = len(started.rows1)
    return Explanation(
        first_pass,
        index.num,
        n1,
        started.n2,
        narrowed.n2 if narrowed is not started else None,
        scorer.scored - n1 if refined else None,
        scorer.scored,
        fp.hint is not None,
    )
