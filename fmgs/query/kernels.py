"""numba kernels for text queries (called from fmgs.query.bounds and certify, which import this module
only when a query needs it): the compact state's int8 coefficients times float32 weights, and dots of
the float16 embeddings decoded exactly.

Each kernel names its exact twin in fmgs.query.reference (float64 numpy or torch). fastmath lets the
compiler reassociate the float32 sums, so a kernel agrees with its twin within the rounding it states.
"""

from __future__ import annotations

import numba
import numpy as np

from fmgs.query.simd import (
    LANES,
    compress_at_least,
    prefetch_row,
    row_dots4,
    row_dots4x3,
    row_dots8,
    row_dots8x3,
    row_tier2_upper8,
    row_upper8,
)


@numba.njit(parallel=True, fastmath=True, cache=True)
def int8_dots(A: np.ndarray, W: np.ndarray, shift: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """out[i,k] = sum_j A[i,j] W[k,j] - shift[i]; A [M,r] int8, W [n,r] float32 (contiguous rows: the
    inner sum vectorises), shift [M], out [M,n]. Twin: ``reference.int8_dots_reference``."""
    M, r = A.shape
    n = W.shape[0]
    for i in numba.prange(M):
        for k in range(n):
            acc = np.float32(0.0)
            for j in range(r):
                acc += np.float32(A[i, j]) * W[k, j]
            out[i, k] = acc - shift[i]


@numba.njit(parallel=True, fastmath=True, cache=True)
def int8_upper(
    A: np.ndarray,
    W: np.ndarray,
    shift: np.ndarray,
    err: np.ndarray,
    res: np.ndarray,
    wn: np.ndarray,
    vn: np.ndarray,
    slack: float,
    out: np.ndarray,
) -> None:  # pragma: no cover
    """out[k,i] = sum_j A[i,j] W[k,j] - shift[i] + err[i] wn[k] + res[i] vn[k] + slack: an upper bound on
    every row's margin for each query (fmgs.query.state); W [nw,r] (nw >= n: rows past n are padding,
    see ``pad_texts``), err, res [M] float32, wn, vn [n]; out [n,M]: each query's bounds contiguous, as
    certification reads them. Twin: ``reference.int8_upper_reference``."""
    M, r = A.shape
    n, nw = out.shape[0], W.shape[0]
    vector = r % LANES == 0
    for i in numba.prange(M):
        k = 0
        if vector:  # fmgs.query.simd: eight (then four) texts per row, one transposing sum
            while k + 7 < n:  # the bound's terms as 8-lane arithmetic too
                a = row_upper8(A, W, i, k, shift, err, res, wn, vn, slack)
                for u in range(8):
                    out[k + u, i] = a[u]
                k += 8
            while k + 3 < n:
                a = row_dots4(A, W, i, k)
                for u in range(4):
                    _put_upper(out, a[u], k + u, i, shift, err, res, wn, vn, slack)
                k += 4
            if k < n and k + 7 < nw:  # padded weights (pad_texts): the last texts in one group
                a = row_dots8(A, W, i, k)
                for u in range(8):
                    if k + u < n:
                        _put_upper(out, a[u], k + u, i, shift, err, res, wn, vn, slack)
                k = n
            elif k < n and k + 3 < nw:
                a = row_dots4(A, W, i, k)
                for u in range(4):
                    if k + u < n:
                        _put_upper(out, a[u], k + u, i, shift, err, res, wn, vn, slack)
                k = n
        elif n >= 4:  # a row converted once, four queries per sweep (for fewer, converting costs more)
            buf = np.empty(r, np.float32)
            for j in range(r):
                buf[j] = np.float32(A[i, j])
            while k + 3 < n:
                a0 = np.float32(0.0)
                a1 = np.float32(0.0)
                a2 = np.float32(0.0)
                a3 = np.float32(0.0)
                for j in range(r):
                    x = buf[j]
                    a0 += x * W[k, j]
                    a1 += x * W[k + 1, j]
                    a2 += x * W[k + 2, j]
                    a3 += x * W[k + 3, j]
                out[k, i] = a0 - shift[i] + err[i] * wn[k] + res[i] * vn[k] + slack
                out[k + 1, i] = a1 - shift[i] + err[i] * wn[k + 1] + res[i] * vn[k + 1] + slack
                out[k + 2, i] = a2 - shift[i] + err[i] * wn[k + 2] + res[i] * vn[k + 2] + slack
                out[k + 3, i] = a3 - shift[i] + err[i] * wn[k + 3] + res[i] * vn[k + 3] + slack
                k += 4
        while k < n:
            acc = np.float32(0.0)
            for j in range(r):
                acc += np.float32(A[i, j]) * W[k, j]
            out[k, i] = acc - shift[i] + err[i] * wn[k] + res[i] * vn[k] + slack
            k += 1


@numba.njit(cache=True)
def at_least(x: np.ndarray, cut: float, out: np.ndarray) -> int:  # pragma: no cover
    """Positions i of x [M] float32 with x[i] >= cut, in order, written to out (int64); returns how many,
    or -1 when out is too small for them (then it holds a part: call again with len(out) >= M + LANES).
    Twin: ``reference.at_least_reference`` (numpy's flatnonzero(x >= cut))."""
    m, i, n = 0, 0, x.shape[0]
    c = np.float32(cut)
    while i + LANES <= n:  # fmgs.query.simd: sixteen values per compare, no branch per value
        if m + LANES > out.shape[0]:
            return -1
        m += compress_at_least(x, i, c, out, m)
        i += LANES
    while i < n:
        if x[i] >= c:
            if m >= out.shape[0]:
                return -1
            out[m] = i
            m += 1
        i += 1
    return m


def pad_texts(*weights: np.ndarray) -> tuple[np.ndarray, ...]:
    """Weights [n,r] with zero rows appended up to a multiple of four when n % 4 is 3, or 2 with n > 2:
    the kernels' vector code then takes the last texts four at a time and writes only the first n.
    Two texts alone are not padded: their pass is bound by reading the codes, and their own loops cost
    less than four texts' products (benchmarks/results/TUNING.md)."""
    n = weights[0].shape[0]
    if n % 4 < 2 or n == 2:
        return weights
    pad = 4 - n % 4
    return tuple(np.concatenate([w, np.zeros((pad, w.shape[1]), w.dtype)]) for w in weights)


_AHEAD_CODES = 8
"""Rows of ``tier2_bounds`` whose codes and norms are asked for ahead of the row being summed."""


@numba.njit(inline="always", cache=True)
def _put_upper(out, a, k, i, shift, err, res, wn, vn, slack):  # pragma: no cover
    out[k, i] = a - shift[i] + err[i] * wn[k] + res[i] * vn[k] + slack


@numba.njit(parallel=True, fastmath=True, cache=True)
def tier2_bounds(
    A1: np.ndarray,
    W1: np.ndarray,
    A2: np.ndarray,
    W2: np.ndarray,
    A3: np.ndarray,
    W3: np.ndarray,
    rows: np.ndarray,
    shift: np.ndarray,
    err1: np.ndarray,
    bounds2: np.ndarray,
    wn1: np.ndarray,
    wn2: np.ndarray,
    vn2: np.ndarray,
    slack: float,
    lo: np.ndarray,
    up: np.ndarray,
) -> None:  # pragma: no cover
    """Float64 bounds lo[k,t] <= f.v_k - shift[i] <= up[k,t] for rows i = rows[t] from both tiers of the
    compact state (fmgs.query.state): a = A1[i].W1[k] + A2[i].W2[k] + A3[i].W3[k] in float32, error
    err1[i] wn1[k] + bounds2[i,0] wn2[k] + bounds2[i,1] vn2[k] + slack (slack covers the float32 sum).
    A1 [M,r1], A2 [M,r2], A3 [M,r3] int8 (the second tier's head and tail; r3 may be 0); W1 [n,r1],
    W2 [n,r2], W3 [n,r3] float32; err1 [M], shift [M] float32; bounds2 [M,2] float32;
    wn1, wn2, vn2 [n] float64; lo, up [n,m] float64; the weights may hold padding rows past n
    (``pad_texts``). Twin: ``reference.tier2_bounds_reference``."""
    n, nw = lo.shape[0], W1.shape[0]
    m = rows.shape[0]
    vector = A1.shape[1] % LANES == 0 and A2.shape[1] % LANES == 0 and A3.shape[1] % LANES == 0
    for t in numba.prange(m):
        if t + _AHEAD_CODES < m:  # sparse rows: their six tables' lines asked for ahead of the sums
            ahead = rows[t + _AHEAD_CODES]
            prefetch_row(A1, ahead)
            prefetch_row(A2, ahead)
            prefetch_row(A3, ahead)
            prefetch_row(shift, ahead)
            prefetch_row(err1, ahead)
            prefetch_row(bounds2, ahead)
        i = rows[t]
        sh, e1, e2, res = _row_terms(shift, err1, bounds2, i)
        k = 0
        if vector:  # fmgs.query.simd
            while k + 7 < n:
                a = row_dots8x3(A1, W1, A2, W2, A3, W3, i, k)
                for u in range(8):
                    _put_tier2(a[u], sh, e1, e2, res, wn1, wn2, vn2, slack, lo, up, k + u, t)
                k += 8
            while k + 3 < n:
                a = row_dots4x3(A1, W1, A2, W2, A3, W3, i, k)
                for u in range(4):
                    _put_tier2(a[u], sh, e1, e2, res, wn1, wn2, vn2, slack, lo, up, k + u, t)
                k += 4
            if k < n and k + 7 < nw:  # padded weights (pad_texts): the last texts in one group
                a = row_dots8x3(A1, W1, A2, W2, A3, W3, i, k)
                for u in range(8):
                    if k + u < n:
                        _put_tier2(a[u], sh, e1, e2, res, wn1, wn2, vn2, slack, lo, up, k + u, t)
                k = n
            elif k < n and k + 3 < nw:
                a = row_dots4x3(A1, W1, A2, W2, A3, W3, i, k)
                for u in range(4):
                    if k + u < n:
                        _put_tier2(a[u], sh, e1, e2, res, wn1, wn2, vn2, slack, lo, up, k + u, t)
                k = n
        while k + 7 < n:  # eight texts per sweep of the row: one conversion feeds eight products
            a = _dots8(A1, W1, A2, W2, A3, W3, i, k)
            for u in range(8):
                _put_tier2(a[u], sh, e1, e2, res, wn1, wn2, vn2, slack, lo, up, k + u, t)
            k += 8
        while k + 3 < n:  # four texts per sweep
            a0, a1, a2, a3 = _dots4(A1, W1, A2, W2, A3, W3, i, k)
            _put_tier2(a0, sh, e1, e2, res, wn1, wn2, vn2, slack, lo, up, k, t)
            _put_tier2(a1, sh, e1, e2, res, wn1, wn2, vn2, slack, lo, up, k + 1, t)
            _put_tier2(a2, sh, e1, e2, res, wn1, wn2, vn2, slack, lo, up, k + 2, t)
            _put_tier2(a3, sh, e1, e2, res, wn1, wn2, vn2, slack, lo, up, k + 3, t)
            k += 4
        while k < n:
            _put_tier2(
                _dots1(A1, W1, A2, W2, A3, W3, i, k), sh, e1, e2, res, wn1, wn2, vn2, slack, lo, up, k, t
            )
            k += 1


@numba.njit(inline="always", cache=True)
def _dots4(A1, W1, A2, W2, A3, W3, i, k):  # pragma: no cover
    """Row i's codes (all tiers) dotted with texts k..k+3's weights, float32, the row converted once."""
    z = np.float32(0.0)
    return _sweep4(A3, W3, i, k, _sweep4(A2, W2, i, k, _sweep4(A1, W1, i, k, (z, z, z, z))))


@numba.njit(inline="always", cache=True)
def _sweep4(A, W, i, k, acc):  # pragma: no cover
    """acc (four float32 sums) plus row i of one tier's codes A dotted with texts k..k+3 of W."""
    a0, a1, a2, a3 = acc
    for j in range(A.shape[1]):
        x = np.float32(A[i, j])
        a0 += x * W[k, j]
        a1 += x * W[k + 1, j]
        a2 += x * W[k + 2, j]
        a3 += x * W[k + 3, j]
    return a0, a1, a2, a3


@numba.njit(inline="always", cache=True)
def _dots8(A1, W1, A2, W2, A3, W3, i, k):  # pragma: no cover
    """``_dots4`` for texts k..k+7: eight independent sums per sweep of the row, not two sweeps of four
    (benchmarks/results/TUNING.md)."""
    z = np.float32(0.0)
    acc = _sweep8(A1, W1, i, k, (z, z, z, z, z, z, z, z))
    return _sweep8(A3, W3, i, k, _sweep8(A2, W2, i, k, acc))


@numba.njit(inline="always", cache=True)
def _sweep8(A, W, i, k, acc):  # pragma: no cover
    """acc (eight float32 sums) plus row i of one tier's codes A dotted with texts k..k+7 of W."""
    a0, a1, a2, a3, a4, a5, a6, a7 = acc
    for j in range(A.shape[1]):
        x = np.float32(A[i, j])
        a0 += x * W[k, j]
        a1 += x * W[k + 1, j]
        a2 += x * W[k + 2, j]
        a3 += x * W[k + 3, j]
        a4 += x * W[k + 4, j]
        a5 += x * W[k + 5, j]
        a6 += x * W[k + 6, j]
        a7 += x * W[k + 7, j]
    return a0, a1, a2, a3, a4, a5, a6, a7


@numba.njit(inline="always", cache=True)
def _dots1(A1, W1, A2, W2, A3, W3, i, k):  # pragma: no cover
    """Row i's codes (all tiers) dotted with text k's weights, float32."""
    a0 = np.float32(0.0)
    for j in range(A1.shape[1]):
        a0 += np.float32(A1[i, j]) * W1[k, j]
    for j in range(A2.shape[1]):
        a0 += np.float32(A2[i, j]) * W2[k, j]
    for j in range(A3.shape[1]):
        a0 += np.float32(A3[i, j]) * W3[k, j]
    return a0


@numba.njit(inline="always", cache=True)
def _row_terms(shift, err1, bounds2, i):  # pragma: no cover
    """Row i's shift and its three error norms, widened to float64."""
    return np.float64(shift[i]), np.float64(err1[i]), np.float64(bounds2[i, 0]), np.float64(bounds2[i, 1])


@numba.njit(inline="always", cache=True)
def _width(e1, e2, res, wn1, wn2, vn2, slack, k):  # pragma: no cover
    """Half-width of text k's bound on a row with error norms e1, e2, res (fmgs.query.state)."""
    return e1 * wn1[k] + e2 * wn2[k] + res * vn2[k] + slack


@numba.njit(inline="always", cache=True)
def _put_tier2(acc, sh, e1, e2, res, wn1, wn2, vn2, slack, lo, up, k, t):  # pragma: no cover
    d = np.float64(acc) - sh
    g = _width(e1, e2, res, wn1, wn2, vn2, slack, k)
    lo[k, t] = d - g
    up[k, t] = d + g


@numba.njit(parallel=True, fastmath=True, cache=True)
def tier2_upper(
    A1: np.ndarray,
    W1: np.ndarray,
    A2: np.ndarray,
    W2: np.ndarray,
    A3: np.ndarray,
    W3: np.ndarray,
    shift: np.ndarray,
    err1: np.ndarray,
    bounds2: np.ndarray,
    wn1: np.ndarray,
    wn2: np.ndarray,
    vn2: np.ndarray,
    slack: float,
    up: np.ndarray,
) -> None:  # pragma: no cover
    """``tier2_bounds``'s upper bound for every row i (up [n,M] float32, rounded up: the float64 bound u
    plus |u| 2^-22 + 1e-30 before float32's round-to-nearest, which moves it by at most |u| 2^-24).
    Twin: ``reference.tier2_bounds_reference``'s upper bound over every row, before that rounding."""
    n, nw = up.shape[0], W1.shape[0]
    vector = A1.shape[1] % LANES == 0 and A2.shape[1] % LANES == 0 and A3.shape[1] % LANES == 0
    for i in numba.prange(A1.shape[0]):
        sh, e1, e2, res = _row_terms(shift, err1, bounds2, i)
        k = 0
        if vector:  # fmgs.query.simd
            while k + 7 < n:  # the bound's float64 terms as 8-lane arithmetic too
                a = row_tier2_upper8(A1, W1, A2, W2, A3, W3, i, k, sh, e1, e2, res, wn1, wn2, vn2, slack)
                for u in range(8):
                    up[k + u, i] = a[u]
                k += 8
            while k + 3 < n:
                a = row_dots4x3(A1, W1, A2, W2, A3, W3, i, k)
                for u in range(4):
                    up[k + u, i] = _up32(a[u], sh, e1, e2, res, wn1, wn2, vn2, slack, k + u)
                k += 4
            if k < n and k + 7 < nw:  # padded weights (pad_texts): the last texts in one group
                a = row_dots8x3(A1, W1, A2, W2, A3, W3, i, k)
                for u in range(8):
                    if k + u < n:
                        up[k + u, i] = _up32(a[u], sh, e1, e2, res, wn1, wn2, vn2, slack, k + u)
                k = n
            elif k < n and k + 3 < nw:
                a = row_dots4x3(A1, W1, A2, W2, A3, W3, i, k)
                for u in range(4):
                    if k + u < n:
                        up[k + u, i] = _up32(a[u], sh, e1, e2, res, wn1, wn2, vn2, slack, k + u)
                k = n
        while k + 7 < n:
            a = _dots8(A1, W1, A2, W2, A3, W3, i, k)
            for u in range(8):
                up[k + u, i] = _up32(a[u], sh, e1, e2, res, wn1, wn2, vn2, slack, k + u)
            k += 8
        while k + 3 < n:
            a0, a1, a2, a3 = _dots4(A1, W1, A2, W2, A3, W3, i, k)
            up[k, i] = _up32(a0, sh, e1, e2, res, wn1, wn2, vn2, slack, k)
            up[k + 1, i] = _up32(a1, sh, e1, e2, res, wn1, wn2, vn2, slack, k + 1)
            up[k + 2, i] = _up32(a2, sh, e1, e2, res, wn1, wn2, vn2, slack, k + 2)
            up[k + 3, i] = _up32(a3, sh, e1, e2, res, wn1, wn2, vn2, slack, k + 3)
            k += 4
        while k < n:
            up[k, i] = _up32(_dots1(A1, W1, A2, W2, A3, W3, i, k), sh, e1, e2, res, wn1, wn2, vn2, slack, k)
            k += 1


@numba.njit(inline="always", cache=True)
def _up32(acc, sh, e1, e2, res, wn1, wn2, vn2, slack, k):  # pragma: no cover
    u = np.float64(acc) - sh + _width(e1, e2, res, wn1, wn2, vn2, slack, k)
    return np.float32(u + abs(u) * 2.0**-22 + 1e-30)


_TWO_M24 = np.float32(2.0**-24)
"""One mantissa unit of a float16 subnormal."""
_REBIAS = np.uint32(112 << 23)
"""float32 exponent bias (127) minus float16's (15), in place: adding it to a normal float16's
exponent-and-mantissa bits shifted to float32's layout gives the float32 bits of the same value."""


@numba.njit(inline="always", cache=True)
def _normal_bits(h):  # pragma: no cover
    """float32 bits of a float16 with bits h (uint32) read as a normal number: exact for exponents 1..30
    (subnormals, zeros, inf and NaN are fixed by _fix_special). Integer work only: it vectorises."""
    return (((h & np.uint32(0x7FFF)) << np.uint32(13)) + _REBIAS) | ((h & np.uint32(0x8000)) << np.uint32(16))


@numba.njit(inline="always", cache=True)
def _fix_special(h, x):  # pragma: no cover
    """The value of the float16 with bits h given x = its _normal_bits as float32: x itself for exponents
    1..30, mantissa * 2^-24 (signed) for zeros and subnormals (a normal float32: no flush to zero), +inf
    for inf and NaN (a damaged row is reported as not finite)."""
    e = h & np.uint32(0x7C00)
    sub = np.float32(h & np.uint32(0x3FF)) * _TWO_M24
    if h & np.uint32(0x8000):
        sub = -sub
    return sub if e == 0 else (np.float32(np.inf) if e == np.uint32(0x7C00) else x)


@numba.njit(inline="always", cache=True)
def _decode_row(A, r, bits, buf):  # pragma: no cover
    """buf[j] = float16 A[r,j] as float32, exactly (bits: a uint32 scratch row, buf: its float32 view)."""
    D = A.shape[1]
    for j in range(D):
        bits[j] = _normal_bits(np.uint32(A[r, j]))
    for j in range(D):
        buf[j] = _fix_special(np.uint32(A[r, j]), buf[j])


@numba.njit(parallel=True, cache=True)
def half_decode(A: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """out [M,D] float32 = the float16 values whose bits are A [M,D] uint16 (inf for inf and NaN); the
    decoding every kernel here uses, exposed for its test against its twin,
    ``reference.half_decode_reference`` (numpy's float16)."""
    for r in numba.prange(A.shape[0]):
        bits = np.empty(A.shape[1], np.uint32)
        buf = bits.view(np.float32)
        _decode_row(A, r, bits, buf)
        out[r] = buf


_POW112 = np.float32(2.0**112)
"""2^(127-15): float16 bits shifted into float32's layout read 2^112 times too small (subnormals too)."""
SUBNORMAL_PROBE = np.array([1], np.uint32).view(np.float32)
"""The smallest float32 subnormal: ``half_dots`` checks in every thread that it survives scaling."""


def half_dots(
    A: np.ndarray,
    rows: np.ndarray,
    V: np.ndarray,
    out: np.ndarray,
    mag: np.ndarray,
    probe: np.ndarray = SUBNORMAL_PROBE,
    scaled: bool = True,
) -> bool:
    """out[t,k] = float32 sum_j A[rows[t],j] V[k,j] and mag[t,k] = sum_j |A V| (any summation order), for
    A [M,D] float16 bits (uint16), V [n,D] float32. The rounding error of out is at most (D+4) 2^-24 mag
    (the bound fmgs.query.bounds uses). Twin: ``reference.half_dots_reference``.

    Fast decoding (``scaled``): a float16's bits shifted into float32's layout, times 2^112 (four integer
    operations and a product per value, twice as fast as decoding the fields). Float16 subnormals then
    pass through float32 subnormals, which a thread with flush-to-zero (e.g. after
    ``torch.set_flush_denormal(True)``) would zero: each block of rows checks ``probe`` (the smallest
    subnormal) the same way, and if any thread flushed it, the call is redone with the field decoding
    (``_decode_row``), exact everywhere. Returns whether it was redone.
    """
    flushed = np.zeros(1, np.uint8)
    _half_dots(A, rows, V, out, mag, scaled, probe, flushed)
    if flushed[0]:
        _half_dots(A, rows, V, out, mag, False, probe, flushed)
    return bool(flushed[0])


@numba.njit(inline="always", cache=True)
def _decode_row_scaled(A, r, bits, buf):  # pragma: no cover
    """buf[j] = float16 A[r,j] as float32 by shifting and scaling (exact unless subnormals are flushed)."""
    D = A.shape[1]
    for j in range(D):
        h = np.uint32(A[r, j])
        bits[j] = ((h & np.uint32(0x7FFF)) << np.uint32(13)) | ((h & np.uint32(0x8000)) << np.uint32(16))
    for j in range(D):
        x = buf[j] * _POW112
        buf[j] = np.float32(np.inf) if abs(x) >= np.float32(65536.0) else x  # inf/NaN exponent


@numba.njit(inline="always", cache=True)
def _decode(A, r, bits, buf, scaled):  # pragma: no cover
    """buf = row r decoded, the fast way (``scaled``) or by fields (see ``half_dots``)."""
    if scaled:
        _decode_row_scaled(A, r, bits, buf)
    else:
        _decode_row(A, r, bits, buf)


@numba.njit(parallel=True, fastmath={"reassoc", "contract", "arcp"}, cache=True)
def _half_dots(A, rows, V, out, mag, scaled, probe, flushed):  # pragma: no cover
    m = rows.shape[0]
    D = A.shape[1]
    n = V.shape[0]
    B = 64
    for b in numba.prange((m + B - 1) // B):
        if scaled and probe[0] * _POW112 == np.float32(0.0):
            flushed[0] = 1
        bits = np.empty(D, np.uint32)
        buf = bits.view(np.float32)
        for t in range(b * B, min(m, (b + 1) * B)):
            _decode(A, rows[t], bits, buf, scaled)
            for k in range(n):
                acc = np.float32(0.0)
                aab = np.float32(0.0)
                for j in range(D):
                    p = buf[j] * V[k, j]
                    acc += p
                    aab += abs(p)
                out[t, k] = acc
                mag[t, k] = aab


def half_bounds(
    A: np.ndarray,
    rows: np.ndarray,
    V: np.ndarray,
    shift: np.ndarray,
    lo: np.ndarray,
    up: np.ndarray,
    probe: np.ndarray = SUBNORMAL_PROBE,
) -> int:
    """Float64 bounds lo[k,t] <= f.V_k - shift[r] <= up[k,t] for rows r = rows[t] of A [M,D] (float16 bits)
    and V [n,D] float32, from one float32 pass (any summation order); shift [M] float32 (widened exactly).
    lo, up [n,m]: one contiguous row per vector, what certification reads per text. Returns the first
    row whose dots are not finite, or -1.

    Bound: a float32 sum of D products in any order is off by at most (D+4) 2^-24 sum_j |f_j V_kj|
    (as ``half_dots``), and sum_j |f_j V_kj| <= |f| |V_k| (Cauchy-Schwarz): the row's norm is summed once
    instead of a magnitude per dot, and texts go through the row two at a time, sharing its loads. The
    norm's float32 sum of squares is low by at most a factor 1 - (D+1) 2^-24 (positive terms), which
    ``grow`` undoes. On unit vectors the bound is about 1.6x looser than the magnitude's, around 5e-5 at
    D = 512, far below the margins' gaps. Subnormals: as ``half_dots``. Twin:
    ``reference.half_dots_reference`` (tests check the bounds hold and are tight)."""
    D = A.shape[1]
    vn = np.sqrt((np.asarray(V, np.float64) ** 2).sum(1))
    c = (D + 4) * 2.0**-24
    grow = (1.0 + 2.0**-20) / np.sqrt(1.0 - (D + 1) * 2.0**-24)
    bad = np.full((len(rows) + 63) // 64, -1, np.int64)
    flushed = np.zeros(1, np.uint8)
    _half_bounds(A, rows, V, shift, vn, c, grow, lo, up, True, probe, flushed, bad)
    if flushed[0]:
        _half_bounds(A, rows, V, shift, vn, c, grow, lo, up, False, probe, flushed, bad)
    hit = bad[bad >= 0]
    return int(hit[0]) if len(hit) else -1


@numba.njit(inline="always", cache=True)
def _put_bounds(acc, nf, vnk, c, sh, lo, up, k, t):  # pragma: no cover
    d = np.float64(acc)
    e = nf * vnk * c + 1e-12
    m = d - sh
    lo[k, t] = m - e
    up[k, t] = m + e
    return np.isfinite(d)


@numba.njit(parallel=True, fastmath={"reassoc", "contract", "arcp"}, cache=True)
def _half_bounds(A, rows, V, shift, vn, c, grow, lo, up, scaled, probe, flushed, bad):  # pragma: no cover
    m = rows.shape[0]
    D = A.shape[1]
    n = V.shape[0]
    B = 64
    for b in numba.prange((m + B - 1) // B):
        if scaled and probe[0] * _POW112 == np.float32(0.0):
            flushed[0] = 1
        bits = np.empty(D, np.uint32)
        buf = bits.view(np.float32)
        bad[b] = -1
        for t in range(b * B, min(m, (b + 1) * B)):
            r = rows[t]
            _decode(A, r, bits, buf, scaled)
            sq = np.float32(0.0)
            for j in range(D):
                sq += buf[j] * buf[j]
            nf = np.sqrt(np.float64(sq)) * grow
            sh = np.float64(shift[r])
            ok = np.isfinite(nf)
            k = 0
            while k + 1 < n:  # two texts per sweep of the row
                a0 = np.float32(0.0)
                a1 = np.float32(0.0)
                for j in range(D):
                    x = buf[j]
                    a0 += x * V[k, j]
                    a1 += x * V[k + 1, j]
                ok &= _put_bounds(a0, nf, vn[k], c, sh, lo, up, k, t)
                ok &= _put_bounds(a1, nf, vn[k + 1], c, sh, lo, up, k + 1, t)
                k += 2
            if k < n:
                a0 = np.float32(0.0)
                for j in range(D):
                    a0 += buf[j] * V[k, j]
                ok &= _put_bounds(a0, nf, vn[k], c, sh, lo, up, k, t)
            if not ok and bad[b] < 0:
                bad[b] = r


def half_dots64(A: np.ndarray, rows: np.ndarray, V: np.ndarray, out: np.ndarray) -> None:
    """out[t,k] = sum_j A[rows[t],j] V[k,j] in float64, summed in order j = 0..D-1 (so equal rows give equal
    sums): the exact score. A [M,D] float16 bits, V [n,D] float64 holding float32 values (each product
    is exact in float64). Twin: ``reference.half_dots_reference`` (bit for bit).

    Rows are decoded exactly (``_decode_row``, then widened) and summed four at a time: the four ordered
    sums are independent chains, and the next rows' cache lines are read ahead so that their misses
    overlap this group's sums (random rows of a memory-mapped table), rather than one scalar loop that
    decodes as it sums (benchmarks/results/TUNING.md)."""
    _half_dots64(A, rows, V, out, np.zeros((len(rows) + 63) // 64, np.uint32))


_AHEAD = 4
"""Rows read ahead of the group being summed."""


@numba.njit(inline="always", cache=True)
def _touch(A, rows, start, stop):  # pragma: no cover
    """A word from every cache line of rows[start:stop] (a read whose misses run ahead of the sums)."""
    s = np.uint32(0)
    for u in range(start, stop):
        r = rows[u]
        for j in range(0, A.shape[1], 32):
            s += np.uint32(A[r, j])
    return s


@numba.njit(parallel=True, cache=True)
def _half_dots64(A, rows, V, out, sink):  # pragma: no cover
    m = rows.shape[0]
    D = A.shape[1]
    n = V.shape[0]
    B = 64
    for b in numba.prange((m + B - 1) // B):
        bits = np.empty(D, np.uint32)
        buf = bits.view(np.float32)
        f = np.zeros((4, D), np.float64)  # a short last group's missing rows hold stale values: not stored
        t = b * B
        end = min(m, t + B)
        s = np.uint32(0)
        while t < end:
            g = min(4, end - t)
            s += _touch(A, rows, t + 4, min(m, t + 4 + _AHEAD))
            for u in range(g):
                _decode_row(A, rows[t + u], bits, buf)
                for j in range(D):
                    f[u, j] = np.float64(buf[j])
            for k in range(n):
                c0 = 0.0
                c1 = 0.0
                c2 = 0.0
                c3 = 0.0
                for j in range(D):
                    v = V[k, j]
                    c0 += f[0, j] * v
                    c1 += f[1, j] * v
                    c2 += f[2, j] * v
                    c3 += f[3, j] * v
                out[t, k] = c0
                if g > 1:
                    out[t + 1, k] = c1
                if g > 2:
                    out[t + 2, k] = c2
                if g > 3:
                    out[t + 3, k] = c3
            t += g
        sink[b] = s  # kept, so the reads ahead are not optimised away


@numba.njit(parallel=True, cache=True)
def float_dots64(A: np.ndarray, rows: np.ndarray, V: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """out[t,k] = sum_j A[rows[t],j] V[k,j] in float64, summed in order j = 0..D-1, for float32 rows A
    [M,D] and V [n,D] float64 holding float32 values (each product is exact in float64): the exact score
    of float32 embeddings, a function of the row alone (a BLAS product's order depends on the batch, so
    equal rows could differ in the last bit). Twin: ``reference.float_dots_reference`` (bit for bit)."""
    D = A.shape[1]
    n = V.shape[0]
    for t in numba.prange(rows.shape[0]):
        r = rows[t]
        for k in range(n):
            c = 0.0
            for j in range(D):
                c += np.float64(A[r, j]) * V[k, j]
            out[t, k] = c
