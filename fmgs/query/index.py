"""The per-Gaussian query state of a scene and certified exact ranking.

Gaussians are ranked by the served margin m_i = f_i.q - max_n f_i.c_n (ties by row), computed in
float64 from the stored embeddings; relevancy = sigmoid(t m_i) orders them the same way but saturates.
Every answer is the exact top K of that ranking, whatever the query (fmgs.query.certify): a cheap pass
gives each row an upper bound on its margin, and rows are rescored exactly until no unscored row can
reach the K-th margin. ``Ranked.rescored`` says how many were; ``EmbeddingIndex.explain`` says which
passes a text took and what each left.

Exact path (small scenes, ``rank=0``, CUDA): the embeddings [M,D] as float32; the pass is one matrix
product, bounded by float32 rounding (about D 2^-24), so only near-ties are rescored.
Compact path (large scenes, CPU): the package's query state (fmgs.query.state: rank-r int8 codes and two
error norms per row, memory-mapped) read by a numba kernel, r bytes per Gaussian; the rows it leaves go
through the state's second tier (the next basis vectors up to the embeddings' numerical rank, read only
for those rows), then a float32 pass over the float16 embeddings (memory-mapped from the package), then
float64. Texts the first tier cannot settle (CLIP-like, absent) start with a pass over every row through
the first tier and the second tier's head, or the whole second tier. Which pass a text takes and what
follows is fmgs.query.plan; the bounds are fmgs.query.bounds. How many rows each step takes depends on
how well the basis describes the scene's embeddings in the query's direction
(benchmarks/results/TEXT.md).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch

from fmgs.checks import check_rows_finite
from fmgs.query import plan, tuning
from fmgs.query.certify import threshold_margin
from fmgs.query.config import IndexConfig
from fmgs.query.plan import NO_PASS, Explanation
from fmgs.query.relevancy import TEMPERATURE
from fmgs.query.state import QueryState, Tier2, build_state

if TYPE_CHECKING:
    from fmgs.query.bounds import CompactBounds, HalfRows

_U32 = 2.0**-24


class Ranked(NamedTuple):
    """Rows of the embedded Gaussians, best first."""

    rows: torch.Tensor
    """[K] int64 rows into the embedded Gaussians (not scene indices)."""
    relevancy: torch.Tensor
    """[K] float32 relevancy in (0,1)."""
    similarity: torch.Tensor
    """[K] float32 f.q."""
    rescored: int = 0
    """Rows scored exactly to certify the answer."""
    margin: torch.Tensor | None = None
    """[K] float64 exact margins (what the ranking orders by; shard answers merge on it)."""


RowReader = Callable[[np.ndarray], torch.Tensor]
"""Exact embeddings for sorted unique rows [k] -> [k,D] float32."""


def served_relevancy(margin: torch.Tensor) -> torch.Tensor:
    """Relevancy as served from float32 margins: float32 of a float64 sigmoid. A float32 sigmoid takes
    a vector path for most elements and a scalar one for the rest, which can differ in the last bit,
    so a row's relevancy would depend on where it sits in the batch (shards would not merge exactly)."""
    return torch.sigmoid(TEMPERATURE * margin.double()).float()


@functools.lru_cache(maxsize=256)
def _threshold_margin(threshold: float) -> float:
    """threshold_margin for the served relevancy (a bisection: computed once per threshold)."""
    return threshold_margin(threshold, served_relevancy)


class EmbeddingIndex:
    """Scores every embedded Gaussian against query vectors; see the module docstring."""

    def __init__(
        self,
        table: torch.Tensor | None,
        canonical: torch.Tensor,
        cfg: IndexConfig,
        state: QueryState | None = None,
        read_rows: RowReader | None = None,
        half: np.ndarray | None = None,
    ) -> None:
        self.table = table
        """[M,D] float32 embeddings on the exact path (None on the compact path)."""
        self.state = state
        """The compact state (None on the exact path)."""
        self.canonical = canonical
        """[M,C] float32 dot products with the scene's canonical phrases (may be memory-mapped)."""
        self.canonical_max = (
            canonical.float().amax(1)
            if canonical.shape[1]
            else torch.zeros(len(canonical), device=canonical.device)
        ).contiguous()
        """[M] the largest canonical dot per Gaussian (float32, as stored)."""
        self.read_rows = read_rows
        """Exact rows of the stored embeddings for rescoring on the compact path when ``half`` is None
        (sorted unique rows [k] -> [k,D] float32); None on the exact path."""
        self.half = half
        """[M,D] uint16: the stored float16 embeddings' bits (None for float32 input), rescored by numba
        kernels on both paths."""
        self.cfg = cfg
        """The settings the index was built with."""
        self.compact: CompactBounds | None = None
        """Bounds from the compact state's tiers (None on the exact path)."""
        self.half_rows: HalfRows | None = None
        """The float16 kernels over ``half`` (None without it)."""
        if state is not None or half is not None:
            # The kernels load numba: imported with the first index that runs them, so importing this
            # module (the server's engine at start, an exact CUDA index) does not.
            from fmgs.query.bounds import CompactBounds, HalfRows

            if half is not None:
                self.half_rows = HalfRows(half, self.canonical_max)
            if state is not None:
                self.compact = CompactBounds(state, self.canonical_max, second_tier=cfg.rank2 > 0)
        self.table_slack: float | None = None
        """Bound on the float32 table's products on the exact path (None on the compact path, whose
        bounds carry their own: ``compact.slack``)."""
        if state is None:
            u = _U32
            if table.is_cuda and torch.backends.cuda.matmul.allow_tf32:
                u = 2.0**-11  # TF32 matmuls keep 10 mantissa bits
            fmax = max(
                (float(table[s : s + 65536].norm(dim=1).max()) for s in range(0, len(table), 65536)),
                default=1.0,
            )
            self.table_slack = 2 * (table.shape[1] + 8) * u * max(1.0, fmax) + 1e-6

    @classmethod
    def build(
        cls,
        embeddings: torch.Tensor,
        canonical: torch.Tensor,
        cfg: IndexConfig = IndexConfig(),
        read_rows: RowReader | None = None,
        state: QueryState | None = None,
    ) -> EmbeddingIndex:
        """From embeddings [M,D] (any float dtype, e.g. a float16 memory map) and canonical dots [M,C].

        ``state``: the package's compact state, used when its rank is the configured one (else one is
        built here). ``read_rows`` supplies exact rows for rescoring on the compact path (default: slices
        of ``embeddings``, which then stay referenced).
        """
        M, D = embeddings.shape
        dev = torch.device(cfg.device)
        if dev.type != "cpu":
            return cls(_float32_on(embeddings, dev), canonical.float().to(dev), cfg)
        # Stored float16 rows are rescored by the fixed-order float64 kernel on both paths, so a row's
        # exact margin never depends on which other rows were scored with it (shards merge bit for bit).
        half = (
            embeddings.view(torch.int16).numpy().view(np.uint16)
            if embeddings.dtype == torch.float16
            else None
        )
        if cfg.rank == 0 or cfg.rank >= D or M < cfg.exact_below:
            return cls(embeddings.float().contiguous(), canonical, cfg, half=half)
        if state is None or state.rank != cfg.rank or state.num != M:
            state = build_state(embeddings, cfg.rank, cfg.basis_sample, cfg.rank2)
        if read_rows is None:
            src = embeddings

            def read_rows(rows: np.ndarray) -> torch.Tensor:
                return src[torch.from_numpy(rows)].float()

        return cls(None, canonical, cfg, state, read_rows, half)

    @property
    def exact(self) -> bool:
        """Whether this is the exact path (the float32 ``table``) rather than the compact one (``state``)."""
        return self.state is None

    @property
    def _first_pass_rows(self) -> torch.Tensor:
        """What every row's first pass reads: the [M,D] float32 table on the exact path, the state's [M,r]
        int8 first-tier codes on the compact path."""
        return self.table if self.state is None else self.state.codes

    @property
    def second_tier(self) -> Tier2 | None:
        """The compact state's second tier as this index reads it (rank, head, tail, whether memory-mapped);
        None on the exact path, when the state has none, or when the settings leave it out (``rank2`` 0)."""
        return self.compact.tier2 if self.compact is not None else None

    @property
    def num(self) -> int:
        """Rows M: the embedded Gaussians."""
        return int(self._first_pass_rows.shape[0])

    def nbytes(self) -> int:
        """Resident bytes per the query state: codes (or float32 table), bound norms, canonical maxima,
        basis; the second tier's codes and bounds only when not memory-mapped, and the resident sample the
        second-tier estimate reads (whether made yet or not). The canonical dots [M,C] are not counted when
        memory-mapped (pose renders page them in)."""
        n = sum(x.numel() * x.element_size() for x in (self._first_pass_rows, self.canonical_max))
        return n + (self.compact.nbytes() if self.compact is not None else 0)

    def basis_nbytes(self) -> int:
        """Bytes of the first tier's basis [r,D] float64 (0 on the exact path): a cost per scene, not per
        Gaussian (benchmarks report the rest of ``nbytes`` per Gaussian)."""
        return 0 if self.state is None else self.state.basis.numel() * self.state.basis.element_size()

    @property
    def device(self) -> torch.device:
        """Where the first pass runs and answers live (a CUDA device only on the exact path)."""
        return self._first_pass_rows.device

    def dots(self, vectors: torch.Tensor, shift: torch.Tensor | None = None) -> torch.Tensor:
        """[M,n] f.v - shift for unit vectors [n,D], the first pass's scores: on the exact path the float32
        table's products (the engine's render and segmentation channels there); on the compact path the
        first tier's int8 approximation, which only ever chooses candidates (renders there use
        ``exact_dots`` of the rows a view touches). shift [M] (default 0) is fused into the kernel. Lives on
        the index's device."""
        v = vectors.float().to(self.device)
        if self.state is None:
            d = self.table @ v.T
            return d if shift is None else d - shift[:, None]
        return self.compact.dots(v, shift)

    def _approx(self, v: torch.Tensor, shift: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Approximate f.v - shift [M,n] and the bound on its error [M,n] (or [1,n] when uniform)."""
        if self.state is None:
            a = self.dots(v, shift)
            return a, torch.full((1, len(v)), self.table_slack, device=a.device)
        return self.compact.first_tier_bounds(v, shift)

    def upper_bounds(self, q: torch.Tensor, canonical_vectors: torch.Tensor | None = None) -> torch.Tensor:
        """[M,n] upper bounds on every row's margin for queries q [n,D] from the cheap pass: the float32
        table on the exact path, the first tier on the compact path (fmgs.query.plan may take a tighter
        pass for some texts). canonical_vectors [C,D] replace the stored canonical dots."""
        n = len(q)
        if canonical_vectors is None:
            if self.state is None:
                a, b = self._approx(q, self.canonical_max)
                return a + b
            return self.compact.first_tier_upper(q)
        a, b = self._approx(torch.cat([q, canonical_vectors.to(q.device)]), None)
        b = b.expand_as(a)
        lower_canon = (a[:, n:] - b[:, n:]).amax(1, keepdim=True)
        return a[:, :n] + b[:, :n] - lower_canon

    def exact_dots(self, rows: torch.Tensor, vectors: torch.Tensor) -> torch.Tensor:
        """[k,n] float64 f.v for rows [k] (any order), from the stored embeddings; on the CPU summed in a
        fixed order (kernels.half_dots64, float_dots64), so a row's value never depends on which rows are
        scored with it (equal rows tie). Rows read through ``read_rows`` or from a CUDA table go
        RESCORE_CHUNK at a time. ValidationError when a stored row is not finite (a damaged package)."""
        v64 = vectors.double().to(self.device)
        r = rows.cpu().numpy()
        uniq, inv = np.unique(r, return_inverse=True)
        out = torch.empty(len(uniq), len(v64), dtype=torch.float64, device=self.device)
        if self.half_rows is not None:  # float64 in a fixed order from the float16 bits (no float64 copy)
            self.half_rows.exact_dots(uniq, v64, out)
        elif self.device.type == "cpu":  # float32 rows, summed in a fixed order too
            from fmgs.query.kernels import float_dots64

            v = v64.numpy()
            if self.state is None:
                float_dots64(self.table.detach().numpy(), uniq.astype(np.int64), v, out.numpy())
            for s in range(0, len(uniq) if self.state is not None else 0, tuning.RESCORE_CHUNK):
                part = uniq[s : s + tuning.RESCORE_CHUNK]
                f = self.read_rows(part).detach().float().contiguous().numpy()
                float_dots64(f, np.arange(len(part)), v, out[s : s + len(part)].numpy())
        else:  # the exact path's CUDA table
            for s in range(0, len(uniq), tuning.RESCORE_CHUNK):
                part = uniq[s : s + tuning.RESCORE_CHUNK]
                f = self.table[torch.from_numpy(part).to(self.device)]
                out[s : s + len(part)] = f.double() @ v64.T
        check_rows_finite(out, uniq)
        return out[torch.from_numpy(inv).to(self.device)]

    def rank(
        self,
        query: torch.Tensor,
        top_k: int,
        threshold: float = 0.0,
        canonical_vectors: torch.Tensor | None = None,
    ) -> Ranked:
        """Exact best ``top_k`` rows for a unit query [D] with relevancy >= threshold (certified).

        canonical_vectors [C,D] replace the scene's canonical phrases (None: the stored dots).
        """
        return self.rank_many(query[None], top_k, threshold, canonical_vectors)[0]

    def rank_many(
        self,
        queries: torch.Tensor,
        top_k: int,
        threshold: float = 0.0,
        canonical_vectors: torch.Tensor | None = None,
        between: Callable[[int], None] | None = None,
    ) -> list[Ranked]:
        """``rank`` for unit queries [n,D], all scored in one pass over the state; ``between(j)`` runs
        before query j is certified (a deadline check may raise there)."""
        k, q, cv = self._request(queries, top_k, canonical_vectors)
        if k == 0 or len(q) == 0:
            e = torch.zeros(0)
            return [Ranked(torch.zeros(0, dtype=torch.int64), e, e, 0) for _ in range(len(q))]
        m_min = _threshold_margin(float(threshold))
        out = []
        for c, scorer in plan.certify_texts(self, q, k, m_min, cv, between):
            sim = scorer.similarity(c.rows)  # every answer row was scored on the way
            rel = served_relevancy(c.margin.float())
            keep = rel >= threshold
            out.append(Ranked(c.rows[keep], rel[keep], sim[keep].float(), c.rescored, c.margin[keep]))
        return out

    def explain(
        self,
        queries: torch.Tensor,
        top_k: int,
        threshold: float = 0.0,
        canonical_vectors: torch.Tensor | None = None,
    ) -> list[Explanation]:
        """How ``rank_many`` certifies each of the unit queries [n,D]: which pass bounded every row (the
        first tier, the first tier and the second tier's head, the whole second tier, or the float32
        table), how many rows were rescored first, how many each later step left, and how many were
        scored exactly in all (fmgs.query.plan.Explanation). Runs the same passes as ``rank_many``."""
        k, q, cv = self._request(queries, top_k, canonical_vectors)
        if k == 0 or len(q) == 0:
            return [Explanation(NO_PASS, self.num, 0, 0, None, None, 0, False) for _ in range(len(q))]
        explained: list[Explanation] = []
        plan.certify_texts(self, q, k, _threshold_margin(float(threshold)), cv, explained=explained)
        return explained

    def _request(
        self, queries: torch.Tensor, top_k: int, canonical_vectors: torch.Tensor | None
    ) -> tuple[int, torch.Tensor, torch.Tensor | None]:
        """(k, queries, canonical vectors) as ranked: k clamped to [0, rows], vectors float32 on the
        index's device."""
        k = max(0, min(int(top_k), self.num))
        if k == 0 or len(queries) == 0:
            return k, queries, None
        q = queries.float().to(self.device)
        cv = None if canonical_vectors is None else canonical_vectors.float().to(self.device)
        return k, q, cv


def _float32_on(embeddings: torch.Tensor, device: torch.device, step: int = 1 << 18) -> torch.Tensor:
    """[M,D] float32 copy of embeddings on ``device``, converted there chunk by chunk (no host-side
    float32 copy of a memory-mapped float16 table)."""
    out = torch.empty(embeddings.shape, dtype=torch.float32, device=device)
    for s in range(0, embeddings.shape[0], step):
        out[s : s + step] = embeddings[s : s + step].to(device, non_blocking=False)
    return out
