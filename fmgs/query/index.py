"""The per-Gaussian query state of a scene and certified exact ranking.

Gaussians are ranked by the served margin m_i = f_i.q - max_n f_i.c_n (ties by row), computed in
float64 from the stored embeddings; relevancy = sigmoid(t m_i) orders them the same way but saturates.
Every answer is the exact top K of that ranking, whatever the query (fmgs.query.certify): a cheap pass
gives each row an upper bound on its margin, and rows are rescored exactly until no unscored row can
reach the K-th margin. ``Ranked.rescored`` says how many were.

Exact path (small scenes, ``rank=0``, CUDA): the embeddings [M,D] as float32; the pass is one matrix
product, bounded by float32 rounding (about D 2^-24), so only near-ties are rescored.
Compact path (large scenes, CPU): the package's query state (fmgs.query.state: rank-r int8 codes and two
error norms per row, memory-mapped) read by a numba kernel, r bytes per Gaussian; the rows it leaves go
through the state's second tier (the next basis vectors up to the embeddings' numerical rank, read only
for those rows), then a float32 pass over the float16 embeddings (memory-mapped from the package), then
float64. Texts the first tier cannot settle (CLIP-like, absent) start with a pass over every row through
the first tier and the second tier's head, or the whole second tier (``_tier2_first``). How many rows
each step takes depends on how well the basis describes the scene's embeddings in the query's direction
(benchmarks/TEXT.md).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch

from fmgs.errors import ValidationError
from fmgs.query import tuning
from fmgs.query.certify import (
    Pending,
    Refined,
    certify_finish,
    certify_narrow,
    certify_start,
    threshold_margin,
)
from fmgs.query.config import IndexConfig
from fmgs.query.relevancy import TEMPERATURE
from fmgs.query.state import QueryState, build_state

_U32 = 2.0**-24


class _Codes(NamedTuple):
    """The compact state's tables as numpy arrays (every row's, or a sample's)."""

    codes1: np.ndarray
    """[m,r] int8 first-tier codes."""
    codes2: np.ndarray
    """[m,h] int8 second-tier codes: its head (all of it when stored whole)."""
    shift: np.ndarray
    """[m] float32 canonical maxima."""
    err1: np.ndarray
    """[m] float32 first-tier quantisation error norms."""
    bounds2: np.ndarray
    """[m,2] float32 second-tier error and residual norms."""
    res1: np.ndarray
    """[m] float32 first-tier residual norms."""
    codes3: np.ndarray
    """[m,r2-h] int8 second-tier codes after the head ([m,0] when stored whole)."""
    head_bounds: np.ndarray
    """[m,2] float32 the head's error and residual norms ([m,0] when stored whole)."""


class _FirstPass(NamedTuple):
    """How each text of a request takes its pass over every row (``_tier2_first``)."""

    direct: list[int]
    """Texts through the whole second tier."""
    head: list[int]
    """Texts through the first tier and the second tier's head."""
    hint: np.ndarray | None
    """[n] float64: each text's cut for certify_start (``_hints``; None: not estimated)."""


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


def _check_finite(values: torch.Tensor, rows: np.ndarray) -> None:
    """ValidationError naming the first stored row whose scores [k,n] are not finite (a damaged package)."""
    if not bool(torch.isfinite(values).all()):
        bad = int(rows[int((~torch.isfinite(values)).any(1).nonzero()[0, 0])])
        raise ValidationError("embeddings", f"row {bad} is not finite: the package is damaged")


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
        self.half = half
        """[M,D] uint16: the stored float16 embeddings' bits (None for float32 input), rescored by numba
        kernels on both paths."""
        self.cfg = cfg
        if state is not None:
            self.coeffs = state.codes
            self.basis = state.basis
            self.scales = state.scales
            self._err = state.err_norm.float().contiguous()
            self._res = state.res_norm.float().contiguous()
            self._W_basis = (state.basis * state.scales.double()[:, None]).contiguous()  # [r,D] float64
            r = state.rank
            self.slack = 8 * (r + 8) * _U32 * max(1.0, state.code_norm_max) + 1e-6
            t2 = state.tier2 if cfg.rank2 > 0 else None
            self.tier2 = t2
            """The state's second tier (None: rows the first leaves go to the float16 embeddings)."""
            if t2 is not None:
                self._W_basis2 = (t2.basis * t2.scales.double()[:, None]).contiguous()  # [r2,D] float64
                self._tail = (
                    t2.tail if t2.tail is not None else torch.empty(len(t2.codes), 0, dtype=torch.int8)
                )
                self._head_bounds = (
                    t2.head_bounds if t2.head_bounds is not None else torch.empty(len(t2.codes), 0)
                )
                self.slack2 = 8 * (r + t2.rank + 8) * _U32 * max(1.0, t2.code_norm_max) + 1e-6
        else:
            self.coeffs = table
            self.basis = self.scales = self.tier2 = None
            u = _U32
            if table.is_cuda and torch.backends.cuda.matmul.allow_tf32:
                u = 2.0**-11  # TF32 matmuls keep 10 mantissa bits
            fmax = max(
                (float(table[s : s + 65536].norm(dim=1).max()) for s in range(0, len(table), 65536)),
                default=1.0,
            )
            self.slack = 2 * (table.shape[1] + 8) * u * max(1.0, fmax) + 1e-6

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
        return self.state is None

    @property
    def num(self) -> int:
        return int(self.coeffs.shape[0])

    def nbytes(self) -> int:
        """Resident bytes per the query state: codes (or float32 table), bound norms, canonical maxima,
        basis; the second tier's codes and bounds only when not memory-mapped, and the resident sample the
        second-tier estimate reads (whether made yet or not). The canonical dots [M,C] are not counted when
        memory-mapped (pose renders page them in)."""
        t = [self.coeffs, self.canonical_max]
        if self.state is not None:
            t += [self._err, self._res, self.basis, self.scales]
        sample = 0
        if self.tier2 is not None:
            t += [self.tier2.basis, self.tier2.scales]
            if not self.tier2.mapped:
                t += [self.tier2.codes, self.tier2.bounds, self._tail, self._head_bounds]
            if self._estimates_first_pass:
                # codes, three norms, bounds2 and the head's bounds (when stored apart)
                per_row = self.state.rank + self.tier2.rank + 4 * 3 + 8 + self._head_bounds.shape[1] * 4
                sample = -(-self.num // tuning.TIER2_FIRST_STEP) * per_row
        return sum(x.numel() * x.element_size() for x in t) + sample

    @property
    def device(self) -> torch.device:
        return self.coeffs.device

    def _weights(self, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Kernel weights [n,r] float32 (= scales * B v), |B v| [n] and |v - B^T B v| [n] (float64 maths)."""
        v64 = v.double()
        w = v64 @ self.basis.T  # [n,r]
        perp = v64 - w @ self.basis
        W = (v64 @ self._W_basis.T).float().contiguous()
        return W, w.norm(dim=1).float(), perp.norm(dim=1).float()

    def dots(self, vectors: torch.Tensor, shift: torch.Tensor | None = None) -> torch.Tensor:
        """[M,n] f.v - shift for unit vectors [n,D] (the compact approximation on the compact path: pose
        renders use it). shift [M] (default 0) is fused into the kernel. Lives on the index's device."""
        v = vectors.float().to(self.device)
        if self.state is None:
            d = self.coeffs @ v.T
            return d if shift is None else d - shift[:, None]
        return self._int8(self._weights(v)[0], shift)

    def _int8(self, W: torch.Tensor, shift: torch.Tensor | None) -> torch.Tensor:
        """[M,n] compact f.v - shift from kernel weights W [n,r]."""
        from fmgs.query.kernels import int8_dots

        out = np.empty((self.num, len(W)), np.float32)
        sh = np.zeros(self.num, np.float32) if shift is None else shift.float().contiguous().numpy()
        int8_dots(self.coeffs.numpy(), W.numpy(), sh, out)
        return torch.from_numpy(out)

    def _bounds(self, v: torch.Tensor, shift: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Approximate f.v - shift [M,n] and the bound on its error [M,n] (or [1,n] when uniform)."""
        if self.state is None:
            a = self.dots(v, shift)
            return a, torch.full((1, len(v)), self.slack, device=a.device)
        W, wn, vn = self._weights(v.float())
        return self._int8(W, shift), self._err[:, None] * wn[None] + self._res[:, None] * vn[
            None
        ] + self.slack

    def _upper(self, q: torch.Tensor, canonical_vectors: torch.Tensor | None) -> torch.Tensor:
        """[M,n] upper bounds on the margins of queries q [n,D]."""
        n = len(q)
        if canonical_vectors is None:
            if self.state is None:
                a, b = self._bounds(q, self.canonical_max)
                return a + b
            from fmgs.query.kernels import int8_upper, pad_texts

            W, wn, vn = self._weights(q)
            out = np.empty((n, self.num), np.float32)
            int8_upper(
                self.coeffs.numpy(), *pad_texts(W.numpy()), self.canonical_max.numpy(), self._err.numpy(),
                self._res.numpy(), wn.numpy(), vn.numpy(), np.float32(self.slack), out,
            )  # fmt: skip
            return torch.from_numpy(out).T  # [M,n] view of per-query rows
        a, b = self._bounds(torch.cat([q, canonical_vectors.to(q.device)]), None)
        b = b.expand_as(a)
        lower_canon = (a[:, n:] - b[:, n:]).amax(1, keepdim=True)
        return a[:, :n] + b[:, :n] - lower_canon

    def exact_dots(self, rows: torch.Tensor, vectors: torch.Tensor) -> torch.Tensor:
        """[k,n] float64 f.v for rows [k] (any order), from the stored embeddings, RESCORE_CHUNK rows at a
        time. ValidationError when a stored row is not finite (a damaged package)."""
        v64 = vectors.double().to(self.device)
        r = rows.cpu().numpy()
        uniq, inv = np.unique(r, return_inverse=True)
        out = torch.empty(len(uniq), len(v64), dtype=torch.float64, device=self.device)
        if self.half is not None:  # float64 in a fixed order from the float16 bits (no float64 copy)
            from fmgs.query.kernels import half_dots64

            half_dots64(self.half, uniq.astype(np.int64), v64.numpy(), out.numpy())
        for s in range(0, len(uniq) if self.half is None else 0, tuning.RESCORE_CHUNK):
            part = uniq[s : s + tuning.RESCORE_CHUNK]
            if self.state is None:
                f = self.table[torch.from_numpy(part).to(self.device)]
            else:
                f = self.read_rows(part)
            out[s : s + len(part)] = f.double() @ v64.T
        _check_finite(out, uniq)
        return out[torch.from_numpy(inv).to(self.device)]

    def _tier2_first(self, q: torch.Tensor, k: int, first: int) -> _FirstPass:
        """Texts whose first-tier bound would leave more than TIER2_FIRST_FRACTION of the rows (CLIP-like
        and absent queries): the head's take their first pass through the first tier and the second
        tier's head when that is estimated to leave at most HEAD_FRACTION of the rows (and no more than
        HEAD_TEXTS texts leave the first tier), the direct ones through the whole second tier over every
        row. Estimated on every TIER2_FIRST_STEP-th row: each pass's upper bounds against the sample's
        best second-tier lower bounds. Also each text's hint for certify_start (``_hints``). Speed
        decisions only: every pass gives exact answers."""
        if not self._estimates_first_pass:
            return _FirstPass([], [], None)
        s = self._sample
        n_s = len(s.shift)
        lo2, up2 = self._tier2_bounds(torch.arange(n_s), q, codes=s)
        W, wn, vn = self._weights(q)
        up1 = (torch.from_numpy(s.codes1).float() @ W.T - torch.from_numpy(s.shift)[:, None]).T  # [n,S]
        up1 = up1 + torch.from_numpy(s.err1) * wn[:, None] + torch.from_numpy(s.res1) * vn[:, None]
        ks = max(1, -(-k // tuning.TIER2_FIRST_STEP))
        best = torch.topk(lo2, min(tuning.HINT_BELOW * ks + 1, n_s), dim=1).values
        L = best[:, min(ks, n_s) - 1, None]  # [n,1]: the sample's ks-th best lower bound
        frac = (up1.double() >= L).double().mean(1)
        second = [j for j in range(len(q)) if float(frac[j]) > tuning.TIER2_FIRST_FRACTION]
        est = up1.double()  # each text's sample bounds from the pass it will take
        head = []
        if second and self._has_head and len(second) <= tuning.HEAD_TEXTS:
            up15 = self._head_upper(q[second], _empty32(len(second), n_s), codes=s).double()
            frac15 = (up15 >= L[second]).double().mean(1)
            head = [j for c, j in enumerate(second) if float(frac15[c]) <= tuning.HEAD_FRACTION]
            est[head] = up15[[second.index(j) for j in head]]
        direct = [j for j in second if j not in head]
        est[direct] = up2[direct]
        return _FirstPass(direct, head, self._hints(est, best[:, -1], first))

    def _hints(self, est: torch.Tensor, low: torch.Tensor, first: int) -> np.ndarray:
        """Each text's hint [n] for certify_start (float32 values as float64), from its sample's upper
        bounds est [n,S] (of the pass it takes) and low [n], the sample's (HINT_BELOW ks + 1)-th best
        lower bound: low enough that the ``first`` rows of highest bound reach it (twice their share of
        the sample, as certify.top_rows estimates), and that, most often, so does every row reaching the
        k-th exact margin (benchmarks/results/TEXT.md, "Tuning constants")."""
        n_s = est.shape[1]
        take = min(n_s, 2 * -(-first * n_s // self.num) + 8)
        top = torch.topk(est, take, dim=1).values[:, -1]
        return torch.minimum(top, low).float().double().numpy()

    @property
    def _has_head(self) -> bool:
        """Whether the second tier is stored as a head and a tail (state version 3)."""
        return self.tier2 is not None and self.tier2.tail is not None

    @property
    def _estimates_first_pass(self) -> bool:
        """Whether ``_tier2_first`` estimates (a second tier, and a sample of TIER2_FIRST_MIN_SAMPLE rows)."""
        return self.tier2 is not None and self.num // tuning.TIER2_FIRST_STEP >= tuning.TIER2_FIRST_MIN_SAMPLE

    @functools.cached_property
    def _sample(self) -> _Codes:
        """Every TIER2_FIRST_STEP-th row's codes and norms, copied together on first use (about 1.1 bytes
        per Gaussian, counted by ``nbytes``): the estimate then reads them in one run instead of a page of
        each memory-mapped table per row."""
        rows = torch.arange(0, self.num, tuning.TIER2_FIRST_STEP)
        return _Codes(
            self.coeffs[rows].contiguous().numpy(),
            self.tier2.codes[rows].contiguous().numpy(),
            self.canonical_max[rows].contiguous().numpy(),
            self._err[rows].contiguous().numpy(),
            self.tier2.bounds[rows].contiguous().numpy(),
            self._res[rows].contiguous().numpy(),
            self._tail[rows].contiguous().numpy(),
            self._head_bounds[rows].contiguous().numpy(),
        )

    @property
    def _codes(self) -> _Codes:
        """Every row's codes and norms, as the tier-2 kernels read them."""
        return _Codes(
            self.coeffs.numpy(), self.tier2.codes.numpy(), self.canonical_max.numpy(), self._err.numpy(),
            self.tier2.bounds.numpy(), self._res.numpy(), self._tail.numpy(), self._head_bounds.numpy(),
        )  # fmt: skip

    def _uppers(self, q: torch.Tensor, cv: torch.Tensor | None, fp: _FirstPass) -> torch.Tensor:
        """[n,M] upper bounds on every row's margin: the first tier's, or for the texts in ``fp.direct``
        the whole second tier's, for those in ``fp.head`` the first tier's and the second's head (both
        rounded up to float32)."""
        n, M = len(q), self.num
        passes = [(fp.direct, self._tier2_upper), (fp.head, self._head_upper)]
        rest = [j for j in range(n) if j not in fp.direct and j not in fp.head]
        if len(rest) == n:
            return self._upper(q, cv).T.contiguous()
        out = _empty32(n, M)
        if rest:
            out[rest] = self._upper(q[rest], cv).T
        for texts, run in passes:
            if len(texts) == n:
                return run(q, out)
            if texts:
                out[texts] = run(q[texts], _empty32(len(texts), M))
        return out

    def _narrow_pending(
        self, pending: list[Pending], q: torch.Tensor, k: int, skip: list[int] = ()
    ) -> list[Pending]:
        """The texts with more than REFINE_ABOVE rows left, narrowed by the second tier's bounds (one pass
        over the union of their rows for all of them); the others as they are.

        The pass runs REFINE_CHUNK rows at a time into reused buffers and keeps, per text, only the rows
        whose second-tier upper bound reaches that text's L: the others are out whatever L becomes (it
        only rises), and their lower bounds, below L, cannot raise it."""
        big = [j for j, p in enumerate(pending) if p.n2 > tuning.REFINE_ABOVE and j not in skip]
        if self.tier2 is None or not big:
            return pending
        union = _union(pending, big, self.num)
        qb = q[big]
        size = min(tuning.REFINE_CHUNK, len(union))
        buf = (
            torch.empty(len(big), size, dtype=torch.float64),
            torch.empty(len(big), size, dtype=torch.float64),
        )
        kept: list[list[tuple[torch.Tensor, ...]]] = [[] for _ in big]
        for s in range(0, len(union), tuning.REFINE_CHUNK):
            part = union[s : s + tuning.REFINE_CHUNK]
            lo, up = (b[:, : len(part)] for b in buf)
            self._tier2_bounds(part, qb, into=(lo, up))
            for c, j in enumerate(big):
                sel = torch.nonzero(up[c] >= pending[j].bound).reshape(-1)
                kept[c].append((part[sel], lo[c, sel], up[c, sel]))
        out = list(pending)
        for c, j in enumerate(big):
            rows, lo, up = (torch.cat(x) for x in zip(*kept[c], strict=True))
            out[j] = certify_narrow(pending[j], k, Refined(rows, lo, up))
        return out

    def _tier2_weights(self, q: torch.Tensor, head: bool = False) -> tuple:
        """Both tiers' kernel weights for queries q [n,D]: W1 [n,r], W2 [n,h] (the head's), W3 [n,r2-h]
        (the tail's) float32 and the norms |B v|, |B2 v|, |v - B^T B v - B2^T B2 v| [n] float64 (float64
        maths). ``head``: for the first tier and the head alone (W3 [n,0]; norms |B v|, |B2a v|,
        |v - B^T B v - B2a^T B2a v|)."""
        v64 = q.double()
        h = self.tier2.head
        w1 = v64 @ self.basis.T
        w2 = v64 @ self.tier2.basis.T
        W1 = (v64 @ self._W_basis.T).float().contiguous().numpy()
        W = (v64 @ self._W_basis2.T).float()
        W2, W3 = W[:, :h].contiguous().numpy(), W[:, h:].contiguous().numpy()
        if head:
            w2, W3 = w2[:, :h], W3[:, :0]
        perp = v64 - w1 @ self.basis - w2 @ self.tier2.basis[: w2.shape[1]]
        return (W1, W2, W3, *(x.norm(dim=1).contiguous().numpy() for x in (w1, w2, perp)))

    def _tier2_bounds(
        self,
        rows: torch.Tensor,
        q: torch.Tensor,
        into: tuple[torch.Tensor, torch.Tensor] | None = None,
        codes: _Codes | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Float64 (lower, upper) [n,k] bounds on the margins of sorted rows [k] for queries q [n,D] from
        both tiers of the compact state (kernels.tier2_bounds), written ``into`` when given. ``codes``:
        the tables the rows index (default: every row's)."""
        from fmgs.query.kernels import pad_texts, tier2_bounds

        c = self._codes if codes is None else codes
        W1, W2, W3, *norms = self._tier2_weights(q)
        W1, W2, W3 = pad_texts(W1, W2, W3)
        if into is None:
            into = tuple(torch.empty(len(q), len(rows), dtype=torch.float64) for _ in range(2))
        lo, up = into
        r = np.ascontiguousarray(rows.numpy(), np.int64)  # no copy for the int64 rows callers pass
        tier2_bounds(
            c.codes1, W1, c.codes2, W2, c.codes3, W3, r, c.shift, c.err1, c.bounds2, *norms, self.slack2,
            lo.numpy(), up.numpy(),
        )  # fmt: skip
        return lo, up

    def _tier2_upper(
        self, q: torch.Tensor, out: torch.Tensor, codes: _Codes | None = None, head: bool = False
    ) -> torch.Tensor:
        """Every row's upper bound [n,m] from both tiers for queries q [n,D], float32 rounded up
        (kernels.tier2_upper), written into ``out`` (contiguous). ``head``: from the first tier and the
        second tier's head alone (the head's norms bound what the tail holds). ``codes``: the tables the
        rows are (default: every row's)."""
        from fmgs.query.kernels import pad_texts, tier2_upper

        c = self._codes if codes is None else codes
        W1, W2, W3, *norms = self._tier2_weights(q, head=head)
        W1, W2, W3 = pad_texts(W1, W2, W3)
        A3, bounds2 = (c.codes3[:, :0], c.head_bounds) if head else (c.codes3, c.bounds2)
        tier2_upper(
            c.codes1, W1, c.codes2, W2, A3, W3, c.shift, c.err1, bounds2, *norms, self.slack2, out.numpy()
        )
        return out

    def _head_upper(self, q: torch.Tensor, out: torch.Tensor, codes: _Codes | None = None) -> torch.Tensor:
        """``_tier2_upper`` from the first tier and the second tier's head alone."""
        return self._tier2_upper(q, out, codes, head=True)

    def _refine_pending(self, pending: list, q: torch.Tensor, cv: torch.Tensor | None) -> dict:
        """Tighter bounds for the texts with more than REFINE_ABOVE rows left: one float32 pass over the
        union of those rows for all of them at once. Returns {text: Refined} over the union (a sorted
        superset of each text's rows2: certify_finish reads it as it is, no per-text gathering)."""
        big = [j for j, p in enumerate(pending) if p.n2 > tuning.REFINE_ABOVE]
        if self.half is None or not big:
            return {}
        union = _union(pending, big, self.num)
        lo = torch.empty(len(big), len(union), dtype=torch.float64)
        up = torch.empty_like(lo)
        for s in range(0, len(union), tuning.REFINE_CHUNK):  # bounded working memory for the kernel's inputs
            part = union[s : s + tuning.REFINE_CHUNK]
            self._refine(part, q[big], cv, (lo[:, s : s + len(part)], up[:, s : s + len(part)]))
        return {j: Refined(union, lo[c], up[c]) for c, j in enumerate(big)}

    def _refine(
        self,
        rows: torch.Tensor,
        q: torch.Tensor,
        cv: torch.Tensor | None,
        into: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Float64 lower and upper bounds [k,n] on the margins of sorted rows [k] for queries q [n,D] from
        one float32 pass over their float16 embeddings; cv [C,D] custom canonical vectors, or None for the
        stored maxima (then one fused kernel, ``half_bounds``, writing [n,k] arrays, ``into`` when given,
        returned transposed; otherwise half_dots: rounding at most (D+4) 2^-24 sum|f_j v_j| per dot)."""
        from fmgs.query.kernels import half_bounds, half_dots

        n = len(q)
        r = rows.numpy().astype(np.int64)
        if cv is None:
            if into is None:
                lo = torch.empty(n, len(r), dtype=torch.float64)
                up = torch.empty_like(lo)
            else:
                lo, up = into
            cmax = self.canonical_max.cpu().numpy()  # float32, widened per row in the kernel
            bad = half_bounds(self.half, r, q.float().contiguous().numpy(), cmax, lo.numpy(), up.numpy())
            if bad >= 0:
                raise ValidationError("embeddings", f"row {bad} is not finite: the package is damaged")
            return lo.T, up.T
        vecs = torch.cat([q, cv])
        v = vecs.float().contiguous().numpy()
        out = np.empty((len(r), len(v)), np.float32)
        mag = np.empty((len(r), len(v)), np.float32)
        half_dots(self.half, r, v, out, mag)
        d = torch.from_numpy(out).double()
        e = torch.from_numpy(mag).double() * ((self.half.shape[1] + 4) * _U32) + 1e-12
        _check_finite(d, r)
        c_hi = (d[:, n:] + e[:, n:]).amax(1, keepdim=True)
        c_lo = (d[:, n:] - e[:, n:]).amax(1, keepdim=True)
        lo, up = d[:, :n] - e[:, :n] - c_hi, d[:, :n] + e[:, :n] - c_lo
        if into is not None:
            into[0].copy_(lo.T)
            into[1].copy_(up.T)
        return lo, up

    def _first(self, k: int) -> int:
        """How many rows of highest bound certification rescores first for the top k: rerank * k, but at
        most REFINE_ABOVE beyond k (a large k would pay float64 rescoring for rows the refinement pass
        settles more cheaply); k on the exact path."""
        if self.state is None:
            return k
        return min(self.num, max(k, min(self.cfg.rerank * k, k + tuning.REFINE_ABOVE)))

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
        M, n = self.num, len(queries)
        k = max(0, min(int(top_k), M))
        if k == 0 or n == 0:
            e = torch.zeros(0)
            return [Ranked(torch.zeros(0, dtype=torch.int64), e, e, 0) for _ in range(n)]
        q = queries.float().to(self.device)
        cv = None if canonical_vectors is None else canonical_vectors.float().to(self.device)
        m_min = _threshold_margin(float(threshold))
        first = self._first(k)
        fp = self._tier2_first(q, k, first) if cv is None else _FirstPass([], [], None)
        upper = self._uppers(q, cv, fp)  # [n,M]: each text's bounds in one run of memory
        # None: margins against the custom vectors. Float32 maxima, widened per scored row (a float64 copy
        # of all M would cost 80 MB of fresh pages per query at 10M Gaussians).
        stored = None if cv is not None else self.canonical_max
        scorers = [
            _Scorer(self, q[j : j + 1] if cv is None else torch.cat([q[j : j + 1], cv]), stored)
            for j in range(n)
        ]
        pending = []
        for j in range(n):
            if between is not None:
                between(j)
            hint = None if fp.hint is None else float(fp.hint[j])
            pending.append(certify_start(upper[j], k, scorers[j], m_min, first, hint))
        if cv is None:
            pending = self._narrow_pending(pending, q, k, skip=fp.direct)
        refined = self._refine_pending(pending, q, cv)
        out = []
        for j, p in enumerate(pending):
            c = certify_finish(p, k, scorers[j], m_min, refined.get(j))
            sim = scorers[j].similarity(c.rows)  # every answer row was scored on the way
            rel = served_relevancy(c.margin.float())
            keep = rel >= threshold
            out.append(Ranked(c.rows[keep], rel[keep], sim[keep].float(), c.rescored, c.margin[keep]))
        return out


class _Scorer:
    """A text's exact margins for rows (certify's ExactScorer), keeping the f.q it computed so the answer's
    similarities are not computed twice (10K float64 dots for k = 10,000)."""

    def __init__(self, index: EmbeddingIndex, vecs: torch.Tensor, cmax: torch.Tensor | None) -> None:
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


def _empty32(n: int, m: int) -> torch.Tensor:
    """An uninitialised float32 [n,m] from numpy's allocator, which asks for huge pages on large arrays:
    torch's large CPU allocations took 10K fresh 4 KB pages (13 ms) per query at 10M Gaussians, numpy's
    152 huge pages for 8 x 10M (measured)."""
    return torch.from_numpy(np.empty((n, m), np.float32))


def _union(pending: list[Pending], texts: list[int], num: int) -> torch.Tensor:
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


def _float32_on(embeddings: torch.Tensor, device: torch.device, step: int = 1 << 18) -> torch.Tensor:
    """[M,D] float32 copy of embeddings on ``device``, converted there chunk by chunk (no host-side
    float32 copy of a memory-mapped float16 table)."""
    out = torch.empty(embeddings.shape, dtype=torch.float32, device=device)
    for s in range(0, embeddings.shape[0], step):
        out[s : s + step] = embeddings[s : s + step].to(device, non_blocking=False)
    return out
