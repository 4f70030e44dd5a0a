"""numba kernel for the compact query state: int8 coefficients times float32 weights (imported lazily).

Twin: ``int8_dots_reference`` (torch, float32). Rounding order differs (fastmath lets the compiler
reassociate the sum of r products), so results agree to a few float32 ulps of the sum's magnitude.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(parallel=True, fastmath=True, cache=True)
def int8_dots(A: np.ndarray, W: np.ndarray, shift: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """out[i,k] = sum_j A[i,j] W[j,k] - shift[i]; A [M,r] int8, W [r,n] float32, shift [M], out [M,n]."""
    M, r = A.shape
    n = W.shape[1]
    for i in numba.prange(M):
        for k in range(n):
            acc = np.float32(0.0)
            for j in range(r):
                acc += np.float32(A[i, j]) * W[j, k]
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
    """out[i,k] = sum_j A[i,j] W[j,k] - shift[i] + err[i] wn[k] + res[i] vn[k] + slack: an upper bound on
    every row's margin per column (fmgs.query.state); err, res [M] float32, wn, vn [n]."""
    M, r = A.shape
    n = W.shape[1]
    for i in numba.prange(M):
        for k in range(n):
            acc = np.float32(0.0)
            for j in range(r):
                acc += np.float32(A[i, j]) * W[j, k]
            out[i, k] = acc - shift[i] + err[i] * wn[k] + res[i] * vn[k] + slack
