"""numba kernel for the compact query state: int8 coefficients times float32 weights (imported lazily).

Twin: ``int8_dots_reference`` (torch, float32). Rounding order differs (fastmath lets the compiler
reassociate the sum of r products), so results agree to a few float32 ulps of the sum's magnitude.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(parallel=True, fastmath=True, cache=True)
def int8_dots(A: np.ndarray, W: np.ndarray, shift: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """out[i,k] = sum_j A[i,j] W[k,j] - shift[i]; A [M,r] int8, W [n,r] float32 (contiguous rows: the
    inner sum vectorises), shift [M], out [M,n]."""
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
    """out[i,k] = sum_j A[i,j] W[k,j] - shift[i] + err[i] wn[k] + res[i] vn[k] + slack: an upper bound on
    every row's margin per column (fmgs.query.state); W [n,r], err, res [M] float32, wn, vn [n]."""
    M, r = A.shape
    n = W.shape[0]
    for i in numba.prange(M):
        for k in range(n):
            acc = np.float32(0.0)
            for j in range(r):
                acc += np.float32(A[i, j]) * W[k, j]
            out[i, k] = acc - shift[i] + err[i] * wn[k] + res[i] * vn[k] + slack


def half_scale_table(dtype=np.float32) -> np.ndarray:
    """[64] the value of one mantissa unit for each (sign, exponent) of a float16 (bits 15..10): x =
    (mantissa | implicit bit) * table[h >> 10], exact; +-inf for the inf/NaN exponent."""
    mag = [2.0**-24] + [2.0 ** (e - 25) for e in range(1, 31)] + [np.inf]
    return np.array(mag + [-x for x in mag], dtype)


@numba.njit(inline="always", cache=True)
def _half_parts(bits):  # pragma: no cover
    """A float16's (integer mantissa with its implicit bit, sign-and-exponent index into
    half_scale_table) from its bits: the value is mantissa * table[index], exactly."""
    h = np.int32(bits)
    i = h >> 10
    return (h & 1023) | (1024 if (i & 31) != 0 else 0), i


def half_dots(
    A: np.ndarray, rows: np.ndarray, V: np.ndarray, P: np.ndarray, out: np.ndarray, mag: np.ndarray
):
    """out[t,k] = float32 sum_j A[rows[t],j] V[k,j] and mag[t,k] = sum_j |A V| (any summation order), for
    A [M,D] float16 bits (uint16), V [n,D] float32, P = half_scale_table(). The rounding error of out is
    at most (D+4) 2^-24 mag (the bound fmgs.query.index uses). One column: decoding fused into the sum;
    several: each row decoded once into a buffer."""
    (_half_dots_one if V.shape[0] == 1 else _half_dots_many)(A, rows, V, P, out, mag)


@numba.njit(parallel=True, fastmath={"reassoc", "contract", "arcp"}, cache=True)
def _half_dots_many(A, rows, V, P, out, mag):  # pragma: no cover
    """half_dots for several columns."""
    m = rows.shape[0]
    D = A.shape[1]
    n = V.shape[0]
    B = 64
    for b in numba.prange((m + B - 1) // B):
        buf = np.empty(D, np.float32)
        for t in range(b * B, min(m, (b + 1) * B)):
            r = rows[t]
            for j in range(D):
                mant, i = _half_parts(A[r, j])
                buf[j] = np.float32(mant) * P[i]
            for k in range(n):
                acc = np.float32(0.0)
                aab = np.float32(0.0)
                for j in range(D):
                    p = buf[j] * V[k, j]
                    acc += p
                    aab += abs(p)
                out[t, k] = acc
                mag[t, k] = aab


@numba.njit(parallel=True, fastmath={"reassoc", "contract", "arcp"}, cache=True)
def _half_dots_one(
    A: np.ndarray, rows: np.ndarray, V: np.ndarray, P: np.ndarray, out: np.ndarray, mag: np.ndarray
):  # pragma: no cover
    """half_dots for one column (decoding fused into the sum)."""
    m = rows.shape[0]
    D = A.shape[1]
    n = V.shape[0]
    for t in numba.prange(m):
        r = rows[t]
        for k in range(n):
            acc = np.float32(0.0)
            aab = np.float32(0.0)
            for j in range(D):
                mant, i = _half_parts(A[r, j])
                p = (np.float32(mant) * P[i]) * V[k, j]
                acc += p
                aab += abs(p)
            out[t, k] = acc
            mag[t, k] = aab


@numba.njit(parallel=True, cache=True)
def half_dots64(
    A: np.ndarray, rows: np.ndarray, V: np.ndarray, P: np.ndarray, out: np.ndarray
) -> None:  # pragma: no cover
    """out[t,k] = sum_j A[rows[t],j] V[k,j] in float64, summed in order j = 0..D-1 (so equal rows give equal
    sums): the exact score. A [M,D] float16 bits, V [n,D] float64 holding float32 values (each product
    is exact in float64), P = half_scale_table(np.float64)."""
    m = rows.shape[0]
    D = A.shape[1]
    n = V.shape[0]
    for t in numba.prange(m):
        r = rows[t]
        for k in range(n):
            acc = 0.0
            for j in range(D):
                mant, i = _half_parts(A[r, j])
                acc += (np.float64(mant) * P[i]) * V[k, j]
            out[t, k] = acc
