"""Bounds on the served margins m_i = f_i.q - max_n f_i.c_n from what an index holds, computed by the
numba kernels of fmgs.query.kernels (their exact twins: fmgs.query.reference).

``CompactBounds``: the compact state's two tiers (fmgs.query.state for the decomposition and its norms):
every row's upper bound from the first tier (r int8 codes a row), from the first tier and the second
tier's head, or from both whole tiers; lower and upper bounds of chosen rows from both tiers.
``HalfRows``: the stored float16 embeddings: float64 dots in a fixed order (the exact score) and
float32 bounds of chosen rows (the refinement before float64).

fmgs.query.index imports this module with the first index that reads either (it loads numba; importing
the index, as the server does at start, does not).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
import torch

from fmgs.checks import check_rows_finite, damaged_embedding
from fmgs.query import tuning
from fmgs.query.kernels import (
    half_bounds,
    half_dots,
    half_dots64,
    int8_dots,
    int8_upper,
    pad_texts,
    tier2_bounds,
    tier2_upper,
)
from fmgs.query.state import QueryState

U32 = 2.0**-24
"""One float32 rounding unit (relative)."""


class TierTables(NamedTuple):
    """The compact state's tables as numpy arrays (every row's, or a sample's), as the tier-2 kernels
    read them."""

    first_codes: np.ndarray
    """[m,r] int8 first-tier codes."""
    head_codes: np.ndarray
    """[m,h] int8 codes of the second tier's head (all of the second tier when it is stored whole)."""
    shift: np.ndarray
    """[m] float32 canonical maxima."""
    first_err: np.ndarray
    """[m] float32 first-tier quantisation error norms."""
    tier2_norms: np.ndarray
    """[m,2] float32 the whole second tier's error and residual norms."""
    first_res: np.ndarray
    """[m] float32 first-tier residual norms."""
    tail_codes: np.ndarray
    """[m,r2-h] int8 codes of the second tier after its head ([m,0] when stored whole)."""
    head_norms: np.ndarray
    """[m,2] float32 the head's error and residual norms ([m,0] when stored whole)."""


class CompactBounds:
    """Bounds from the compact state's tiers for queries q [n,D] (unit vectors)."""

    def __init__(self, state: QueryState, canonical_max: torch.Tensor, second_tier: bool = True) -> None:
        """``canonical_max`` [M] float32: each row's largest canonical dot (the index's); ``second_tier``:
        use the state's second tier when it has one."""
        self.state = state
        self.codes = state.codes
        """[M,r] int8 first-tier codes (memory-mapped when loaded from a package)."""
        self.basis = state.basis
        self.canonical_max = canonical_max
        self.err = state.err_norm.float().contiguous()
        """[M] float32 first-tier quantisation error norms."""
        self.res = state.res_norm.float().contiguous()
        """[M] float32 first-tier residual norms."""
        self.weighted_basis = (state.basis * state.scales.double()[:, None]).contiguous()
        """[r,D] float64 scales * B: the first tier's kernel weights are weighted_basis . v."""
        self.slack = 8 * (state.rank + 8) * U32 * max(1.0, state.code_norm_max) + 1e-6
        """Bound on the first tier's float32 sums."""
        t2 = state.tier2 if second_tier else None
        self.tier2 = t2
        """The state's second tier (None: rows the first leaves go to the float16 embeddings)."""
        if t2 is not None:
            self.weighted_basis2 = (t2.basis * t2.scales.double()[:, None]).contiguous()
            """[r2,D] float64 the second tier's scales * B2."""
            self.tail = t2.tail if t2.tail is not None else torch.empty(len(t2.codes), 0, dtype=torch.int8)
            """[M,r2-h] int8 the tail's codes ([M,0] when the tier is stored whole)."""
            self.head_norms = t2.head_bounds if t2.head_bounds is not None else torch.empty(len(t2.codes), 0)
            """[M,2] float32 the head's error and residual norms ([M,0] when stored whole)."""
            self.slack2 = 8 * (state.rank + t2.rank + 8) * U32 * max(1.0, t2.code_norm_max) + 1e-6
            """Bound on both tiers' float32 sums."""

    @property
    def num(self) -> int:
        return int(self.codes.shape[0])

    @property
    def has_head(self) -> bool:
        """Whether the second tier is stored as a head and a tail (a head pass is possible)."""
        return self.tier2 is not None and self.tier2.tail is not None

    def nbytes(self) -> int:
        """Resident bytes beyond the codes: bound norms and bases; the second tier's codes and norms when
        not memory-mapped, and the sample the first-pass estimate reads (whether made yet or not)."""
        t = [self.err, self.res, self.basis, self.state.scales]
        sample = 0
        if self.tier2 is not None:
            t += [self.tier2.basis, self.tier2.scales]
            if not self.tier2.mapped:
                t += [self.tier2.codes, self.tier2.bounds, self.tail, self.head_norms]
            if self.estimates_first_pass:
                # codes, three norms, the second tier's norms and the head's (when stored apart)
                per_row = self.state.rank + self.tier2.rank + 4 * 3 + 8 + self.head_norms.shape[1] * 4
                sample = -(-self.num // tuning.TIER2_FIRST_STEP) * per_row
        return sum(x.numel() * x.element_size() for x in t) + sample

    # ------------------------------------------------------------------------------------- first tier

    def first_tier_weights(self, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Kernel weights [n,r] float32 (= scales * B v), |B v| [n] and |v - B^T B v| [n] float32, for
        vectors v [n,D] (float64 maths)."""
        v64 = v.double()
        w = v64 @ self.basis.T  # [n,r]
        perp = v64 - w @ self.basis
        W = (v64 @ self.weighted_basis.T).float().contiguous()
        return W, w.norm(dim=1).float(), perp.norm(dim=1).float()

    def dots(self, v: torch.Tensor, shift: torch.Tensor | None = None) -> torch.Tensor:
        """[M,n] compact f.v - shift for vectors v [n,D] float32 (kernels.int8_dots); shift [M] or None
        (0)."""
        return self._int8(self.first_tier_weights(v)[0], shift)

    def _int8(self, W: torch.Tensor, shift: torch.Tensor | None) -> torch.Tensor:
        """[M,n] compact f.v - shift from kernel weights W [n,r]."""
        out = np.empty((self.num, len(W)), np.float32)
        sh = np.zeros(self.num, np.float32) if shift is None else shift.float().contiguous().numpy()
        int8_dots(self.codes.numpy(), W.numpy(), sh, out)
        return torch.from_numpy(out)

    def first_tier_bounds(
        self, v: torch.Tensor, shift: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Compact f.v - shift [M,n] for vectors v [n,D] and the bound on its error [M,n]."""
        W, wn, vn = self.first_tier_weights(v.float())
        return self._int8(W, shift), self.err[:, None] * wn[None] + self.res[:, None] * vn[None] + self.slack

    def first_tier_upper(self, q: torch.Tensor) -> torch.Tensor:
        """[M,n] upper bounds on every row's margin (against the stored canonical maxima) for queries q
        [n,D], float32 (kernels.int8_upper): a view of [n,M], each query's bounds contiguous."""
        W, wn, vn = self.first_tier_weights(q)
        out = np.empty((len(q), self.num), np.float32)
        int8_upper(
            self.codes.numpy(), *pad_texts(W.numpy()), self.canonical_max.numpy(), self.err.numpy(),
            self.res.numpy(), wn.numpy(), vn.numpy(), np.float32(self.slack), out,
        )  # fmt: skip
        return torch.from_numpy(out).T

    # ------------------------------------------------------------------------------------ second tier

    @property
    def tables(self) -> TierTables:
        """Every row's codes and norms, as the tier-2 kernels read them."""
        t2 = self.tier2
        return TierTables(
            self.codes.numpy(), t2.codes.numpy(), self.canonical_max.numpy(), self.err.numpy(),
            t2.bounds.numpy(), self.res.numpy(), self.tail.numpy(), self.head_norms.numpy(),
        )  # fmt: skip

    @property
    def estimates_first_pass(self) -> bool:
        """Whether each text's first pass is estimated on a sample (fmgs.query.plan.choose_first_pass): a
        second tier, and a sample of at least TIER2_FIRST_MIN_SAMPLE rows."""
        return self.tier2 is not None and self.num // tuning.TIER2_FIRST_STEP >= tuning.TIER2_FIRST_MIN_SAMPLE

    @functools.cached_property
    def sample(self) -> TierTables:
        """Every TIER2_FIRST_STEP-th row's codes and norms, copied together on first use (about 1.1 bytes
        per Gaussian, counted by ``nbytes``): the estimate then reads them in one run instead of a page of
        each memory-mapped table per row."""
        rows = torch.arange(0, self.num, tuning.TIER2_FIRST_STEP)
        return TierTables(
            self.codes[rows].contiguous().numpy(),
            self.tier2.codes[rows].contiguous().numpy(),
            self.canonical_max[rows].contiguous().numpy(),
            self.err[rows].contiguous().numpy(),
            self.tier2.bounds[rows].contiguous().numpy(),
            self.res[rows].contiguous().numpy(),
            self.tail[rows].contiguous().numpy(),
            self.head_norms[rows].contiguous().numpy(),
        )

    def sample_first_tier_upper(self, q: torch.Tensor) -> torch.Tensor:
        """[n,S] float32 the sample's first-tier upper bounds for queries q [n,D], by torch's matrix
        product (an estimate's input: not the kernel's summation order)."""
        s = self.sample
        W, wn, vn = self.first_tier_weights(q)
        up1 = (torch.from_numpy(s.first_codes).float() @ W.T - torch.from_numpy(s.shift)[:, None]).T
        return up1 + torch.from_numpy(s.first_err) * wn[:, None] + torch.from_numpy(s.first_res) * vn[:, None]

    def tier2_weights(self, q: torch.Tensor, head: bool = False) -> tuple:
        """Both tiers' kernel weights for queries q [n,D]: W1 [n,r], W2 [n,h] (the head's), W3 [n,r2-h]
        (the tail's) float32 and the norms |B v|, |B2 v|, |v - B^T B v - B2^T B2 v| [n] float64 (float64
        maths), as numpy arrays. ``head``: for the first tier and the head alone (W3 [n,0]; norms |B v|,
        |B2a v|, |v - B^T B v - B2a^T B2a v|)."""
        v64 = q.double()
        h = self.tier2.head
        w1 = v64 @ self.basis.T
        w2 = v64 @ self.tier2.basis.T
        W1 = (v64 @ self.weighted_basis.T).float().contiguous().numpy()
        W = (v64 @ self.weighted_basis2.T).float()
        W2, W3 = W[:, :h].contiguous().numpy(), W[:, h:].contiguous().numpy()
        if head:
            w2, W3 = w2[:, :h], W3[:, :0]
        perp = v64 - w1 @ self.basis - w2 @ self.tier2.basis[: w2.shape[1]]
        return (W1, W2, W3, *(x.norm(dim=1).contiguous().numpy() for x in (w1, w2, perp)))

    def tier2_bounds(
        self,
        rows: torch.Tensor,
        q: torch.Tensor,
        into: tuple[torch.Tensor, torch.Tensor] | None = None,
        tables: TierTables | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Float64 (lower, upper) [n,k] bounds on the margins of sorted rows [k] for queries q [n,D] from
        both tiers (kernels.tier2_bounds), written ``into`` when given. ``tables``: the tables the rows
        index (default: every row's)."""
        c = self.tables if tables is None else tables
        W1, W2, W3, *norms = self.tier2_weights(q)
        W1, W2, W3 = pad_texts(W1, W2, W3)
        if into is None:
            into = tuple(torch.empty(len(q), len(rows), dtype=torch.float64) for _ in range(2))
        lo, up = into
        r = np.ascontiguousarray(rows.numpy(), np.int64)  # no copy for the int64 rows callers pass
        tier2_bounds(
            c.first_codes, W1, c.head_codes, W2, c.tail_codes, W3, r, c.shift, c.first_err, c.tier2_norms,
            *norms, self.slack2, lo.numpy(), up.numpy(),
        )  # fmt: skip
        return lo, up

    def tier2_upper(
        self, q: torch.Tensor, out: torch.Tensor, tables: TierTables | None = None, head: bool = False
    ) -> torch.Tensor:
        """Every row's upper bound [n,m] from both tiers for queries q [n,D], float32 rounded up
        (kernels.tier2_upper), written into ``out`` (contiguous) and returned. ``head``: from the first
        tier and the second tier's head alone (the head's norms bound what the tail holds). ``tables``:
        the rows' tables (default: every row's)."""
        c = self.tables if tables is None else tables
        W1, W2, W3, *norms = self.tier2_weights(q, head=head)
        W1, W2, W3 = pad_texts(W1, W2, W3)
        A3, norms2 = (c.tail_codes[:, :0], c.head_norms) if head else (c.tail_codes, c.tier2_norms)
        tier2_upper(
            c.first_codes, W1, c.head_codes, W2, A3, W3, c.shift, c.first_err, norms2, *norms, self.slack2,
            out.numpy(),
        )  # fmt: skip
        return out


class HalfRows:
    """The stored float16 embeddings, read by the float16 kernels on both index paths."""

    def __init__(self, half: np.ndarray, canonical_max: torch.Tensor) -> None:
        """``half`` [M,D] uint16: the float16 embeddings' bits; ``canonical_max`` [M] float32: each row's
        largest canonical dot."""
        self.half = half
        self.canonical_max = canonical_max

    def exact_dots(self, rows: np.ndarray, v64: torch.Tensor, out: torch.Tensor) -> None:
        """out [k,n] float64 = f.v for sorted unique rows [k] and vectors v64 [n,D] float64 holding
        float32 values, summed in a fixed order from the float16 bits (kernels.half_dots64): a row's
        score never depends on which other rows are scored with it."""
        half_dots64(self.half, rows.astype(np.int64), v64.numpy(), out.numpy())

    def refine(
        self,
        rows: torch.Tensor,
        q: torch.Tensor,
        cv: torch.Tensor | None,
        into: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Float64 lower and upper bounds [k,n] on the margins of sorted rows [k] for queries q [n,D] from
        one float32 pass over their float16 embeddings; cv [C,D] custom canonical vectors, or None for the
        stored maxima (then one fused kernel, ``half_bounds``, writing [n,k] arrays, ``into`` when given,
        returned transposed; otherwise half_dots: rounding at most (D+4) 2^-24 sum|f_j v_j| per dot).
        ValidationError names a row that is not finite (a damaged package)."""
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
                raise damaged_embedding(bad)
            return lo.T, up.T
        vecs = torch.cat([q, cv])
        v = vecs.float().contiguous().numpy()
        out = np.empty((len(r), len(v)), np.float32)
        mag = np.empty((len(r), len(v)), np.float32)
        half_dots(self.half, r, v, out, mag)
        d = torch.from_numpy(out).double()
        e = torch.from_numpy(mag).double() * ((self.half.shape[1] + 4) * U32) + 1e-12
        check_rows_finite(d, r)
        c_hi = (d[:, n:] + e[:, n:]).amax(1, keepdim=True)
        c_lo = (d[:, n:] - e[:, n:]).amax(1, keepdim=True)
        lo, up = d[:, :n] - e[:, :n] - c_hi, d[:, :n] + e[:, :n] - c_lo
        if into is not None:
            into[0].copy_(lo.T)
            into[1].copy_(up.T)
        return lo, up
