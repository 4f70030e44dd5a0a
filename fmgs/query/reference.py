"""The exact twins of the text query's fast code, in float64 numpy or torch: each kernel of
fmgs.query.kernels names its twin here, and the tests check the kernel against it (within the kernel's
stated rounding, or bit for bit where the kernel claims that).

No numba: importing this module compiles nothing.
"""

from __future__ import annotations

import numpy as np
import torch

from fmgs.query.certify import order_rows
from fmgs.query.index import Ranked, served_relevancy


def rank_reference(
    embeddings: torch.Tensor, canonical: torch.Tensor, query: torch.Tensor, top_k: int, threshold: float = 0.0
) -> Ranked:
    """Twin of ``EmbeddingIndex.rank`` by brute force in float64: embeddings [M,D], canonical dots [M,C],
    query [D]."""
    sim = embeddings.double() @ query.float().double()
    m = sim - (canonical.float().amax(1).double() if canonical.shape[1] else 0.0)
    rows = torch.arange(len(sim))
    order = order_rows(m, rows)[: max(0, min(int(top_k), len(sim)))]
    rel = served_relevancy(m[order].float())
    keep = rel >= threshold
    return Ranked(rows[order][keep], rel[keep], sim[order][keep].float(), len(sim), m[order][keep])


def int8_dots_reference(
    coeffs: torch.Tensor, scales: torch.Tensor, basis: torch.Tensor, v: torch.Tensor
) -> torch.Tensor:
    """Twin of ``kernels.int8_dots`` as ``EmbeddingIndex.dots`` calls it: [M,n] float32 (dequantised
    coefficients) . (B v) for int8 coefficients [M,r], scales [r], basis [r,D] and vectors v [n,D]."""
    return ((coeffs.double() * scales.double()) @ (v.double() @ basis.T).T).float()


def int8_upper_reference(
    A: np.ndarray,
    W: np.ndarray,
    shift: np.ndarray,
    err: np.ndarray,
    res: np.ndarray,
    wn: np.ndarray,
    vn: np.ndarray,
    slack: float,
) -> np.ndarray:
    """Twin of ``kernels.int8_upper`` in float64: [n,M] sum_j A[i,j] W[k,j] - shift[i] + err[i] wn[k] +
    res[i] vn[k] + slack, for A [M,r] int8, W [n,r] (no padding rows), shift, err, res [M], wn, vn [n]."""
    e, v = err.astype(np.float64), res.astype(np.float64)
    ew, rv = e[None] * wn[:, None], v[None] * vn[:, None]
    return (A.astype(np.float64) @ W.astype(np.float64).T).T - shift[None] + ew + rv + slack


def tier2_bounds_reference(A1, W1, A2, W2, A3, W3, rows, shift, err1, bounds2, wn1, wn2, vn2, slack):
    """Twin of ``kernels.tier2_bounds`` in float64 numpy: (lo, up) [n,m]. Its upper bound over every row
    is the twin of ``kernels.tier2_upper`` before that kernel rounds it up to float32."""
    a = sum(A[rows].astype(np.float64) @ W.astype(np.float64).T for A, W in ((A1, W1), (A2, W2), (A3, W3)))
    d = a - shift[rows].astype(np.float64)[:, None]
    b2 = bounds2[rows].astype(np.float64)
    g = err1[rows].astype(np.float64)[:, None] * wn1[None] + b2[:, :1] * wn2[None] + b2[:, 1:] * vn2[None]
    g = g + slack
    return (d - g).T, (d + g).T


def half_decode_reference(bits: np.ndarray) -> np.ndarray:
    """Twin of ``kernels.half_decode``: the float16 values whose bits are ``bits`` (uint16) as float32,
    by numpy's decoding, with inf for inf and NaN."""
    f = bits.view(np.float16).astype(np.float32)
    f[~np.isfinite(f)] = np.inf
    return f


def half_dots_reference(A: np.ndarray, rows: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Twin of ``kernels.half_dots``, ``half_dots64`` and ``half_bounds``: [m,n] float64 dots of the
    float16 rows (numpy's decoding, inf for inf and NaN) with V, summed in order j = 0..D-1."""
    f = A[rows].view(np.float16).astype(np.float64)
    f[~np.isfinite(f)] = np.inf
    out = np.zeros((len(rows), len(V)))
    for j in range(A.shape[1]):  # in order, as half_dots64
        out += f[:, j : j + 1] * np.asarray(V, np.float64)[None, :, j]
    return out


def float_dots_reference(A: np.ndarray, rows: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Twin of ``kernels.float_dots64``: [m,n] float64 dots of the float32 rows A[rows] with V, summed in
    order j = 0..D-1."""
    f = A[rows].astype(np.float64)
    out = np.zeros((len(rows), len(V)))
    for j in range(A.shape[1]):
        out += f[:, j : j + 1] * np.asarray(V, np.float64)[None, :, j]
    return out


def at_least_reference(x: np.ndarray, cut: float) -> np.ndarray:
    """Twin of ``kernels.at_least`` (and ``simd.compress_at_least``): positions [m] int64 of x [M]
    float32 with x >= float32(cut), in order."""
    return np.flatnonzero(x >= np.float32(cut))
