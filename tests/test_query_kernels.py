"""The float16 kernels of the text query against their float64 twin: exact decoding of every bit
pattern, the float32 pass within its stated rounding bound, the float64 pass equal to the ordered sum."""

from __future__ import annotations

import numpy as np
import pytest

from fmgs.query import kernels


def _numpy_decode(bits: np.ndarray) -> np.ndarray:
    f = bits.view(np.float16).astype(np.float32)
    f[~np.isfinite(f)] = np.inf
    return f


def test_every_float16_bit_pattern_decodes_exactly():
    allbits = np.arange(65536, dtype=np.uint32).astype(np.uint16).reshape(256, 256)
    out = np.empty((256, 256), np.float32)
    kernels.half_decode(allbits, out)
    ref = _numpy_decode(allbits)
    assert np.array_equal(out.view(np.uint32), ref.view(np.uint32))  # signed zeros and subnormals too


def _rows_with_extremes(M: int = 300, D: int = 67, seed: int = 0) -> np.ndarray:
    """[M,D] float16 bits: unit-scale rows, then rows of subnormals, signed zeros, the largest finite
    values and mixtures (D odd: no kernel may assume a multiple of the vector width)."""
    rng = np.random.default_rng(seed)
    f = (rng.standard_normal((M, D)) / np.sqrt(D)).astype(np.float16)
    f[1] = (rng.integers(1, 1024, D) * 2.0**-24).astype(np.float16) * rng.choice([-1, 1], D)  # subnormal
    f[2] = np.float16(-0.0)
    f[3] = rng.choice([65504.0, -65504.0, 6.1e-5, -(2.0**-24)], D).astype(np.float16)
    f[4, ::3] = (rng.integers(1, 1024, len(f[4, ::3])) * 2.0**-24).astype(np.float16)  # mixed
    return f.view(np.uint16)


@pytest.mark.parametrize("n", [1, 3, 8])
@pytest.mark.parametrize("flush", [False, True])
def test_float32_pass_is_within_its_bound(n, flush):
    A = _rows_with_extremes()
    rng = np.random.default_rng(n)
    V = rng.standard_normal((n, A.shape[1])).astype(np.float32)
    V /= np.linalg.norm(V, axis=1, keepdims=True)
    rows = np.array([0, 1, 2, 3, 4, *rng.choice(np.arange(5, len(A)), 100, replace=False)], np.int64)
    out = np.empty((len(rows), n), np.float32)
    mag = np.empty_like(out)
    # A zero probe reads as a thread that flushes subnormals: the call must fall back to field decoding.
    probe = np.zeros(1, np.float32) if flush else kernels.SUBNORMAL_PROBE
    assert kernels.half_dots(A, rows, V, out, mag, probe) is flush
    ref = kernels.half_dots_reference(A, rows, V)
    absref = np.abs(_numpy_decode(A[rows]).astype(np.float64)) @ np.abs(V.astype(np.float64)).T
    bound = (A.shape[1] + 4) * 2.0**-24 * mag
    assert np.all(np.abs(out - ref) <= bound)
    assert np.all(np.abs(mag - absref) <= bound)  # mag is the sum of |products| it claims to be
    assert np.all(out[1] != 0)  # subnormal rows are not flushed to zero


def test_float32_pass_reports_a_damaged_row_as_not_finite():
    A = _rows_with_extremes(M=8)
    A[5, 7] = np.float16(np.inf).view(np.uint16)
    A[6, 0] = np.float16(np.nan).view(np.uint16)
    V = np.ones((2, A.shape[1]), np.float32) / np.sqrt(A.shape[1])
    rows = np.arange(8, dtype=np.int64)
    out, mag = np.empty((8, 2), np.float32), np.empty((8, 2), np.float32)
    kernels.half_dots(A, rows, V, out, mag)
    assert not np.isfinite(out[5]).any() and not np.isfinite(out[6]).any()
    assert np.isfinite(out[[0, 1, 2, 3, 4, 7]]).all()


def test_float64_pass_equals_the_ordered_sum():
    A = _rows_with_extremes()
    V = np.random.default_rng(3).standard_normal((2, A.shape[1])).astype(np.float32).astype(np.float64)
    rows = np.arange(len(A), dtype=np.int64)[::-1].copy()
    out = np.empty((len(rows), 2))
    kernels.half_dots64(A, rows, V, out)
    assert np.array_equal(out, kernels.half_dots_reference(A, rows, V))
    # Every group size (rows are summed four at a time, 64 per block) and text count; repeated rows.
    for m in (1, 2, 3, 5, 63, 64, 65, 130):
        r = np.random.default_rng(m).integers(0, len(A), m).astype(np.int64)
        for n in (1, 3):
            o = np.empty((m, n))
            kernels.half_dots64(A, r, V[:1].repeat(n, 0) * np.arange(1, n + 1)[:, None], o)
            assert np.array_equal(
                o, kernels.half_dots_reference(A, r, V[:1].repeat(n, 0) * np.arange(1, n + 1)[:, None])
            )


def test_float64_pass_reads_damaged_values_as_infinite():
    """inf, -inf and NaN read as +inf (as the twin decodes them), so a damaged row is never finite."""
    A = _rows_with_extremes(M=12)
    for row, bits in ((2, 0x7C00), (5, 0xFC00), (7, 0x7E00), (9, 0xFE01)):
        A[row, 3] = bits
    V = np.ones((1, A.shape[1])) / A.shape[1]
    rows = np.arange(12, dtype=np.int64)
    out = np.empty((12, 1))
    kernels.half_dots64(A, rows, V, out)
    assert np.array_equal(out, kernels.half_dots_reference(A, rows, V), equal_nan=True)
    assert np.isposinf(out[[2, 5, 7, 9], 0]).all() and np.isfinite(out[[0, 1, 3, 4, 6, 8, 10, 11]]).all()


@pytest.mark.parametrize("n", [1, 3, 8])
@pytest.mark.parametrize("flush", [False, True])
def test_fused_bounds_hold_and_are_tight(n, flush):
    A = _rows_with_extremes()
    rng = np.random.default_rng(10 + n)
    V = rng.standard_normal((n, A.shape[1])).astype(np.float32)
    V /= np.linalg.norm(V, axis=1, keepdims=True)
    shift = rng.standard_normal(len(A)).astype(np.float32)
    rows = np.array([3, 0, 1, 2, 4, *rng.choice(np.arange(5, len(A)), 100, replace=False)], np.int64)
    lo, up = np.empty((n, len(rows))), np.empty((n, len(rows)))
    probe = np.zeros(1, np.float32) if flush else kernels.SUBNORMAL_PROBE
    assert kernels.half_bounds(A, rows, V, shift, lo, up, probe) == -1
    exact = kernels.half_dots_reference(A, rows, V).T - shift[rows].astype(np.float64)[None]
    assert np.all(lo <= exact) and np.all(exact <= up)
    f = _numpy_decode(A[rows]).astype(np.float64)
    width = (A.shape[1] + 4) * 2.0**-24 * np.linalg.norm(f, axis=1)[None] * 1.0001 + 2.1e-12
    assert np.all(up - lo <= 2 * width)  # no looser than Cauchy-Schwarz says
    normal = np.abs(f).max(1) < 10  # unit-scale rows: the interval is far below margins' gaps
    assert float((up - lo)[:, normal].max()) < 1e-4


def test_fused_bounds_name_the_first_damaged_row():
    A = _rows_with_extremes(M=200)
    A[150, 7] = np.float16(np.inf).view(np.uint16)
    A[90, 0] = np.float16(np.nan).view(np.uint16)
    V = np.ones((2, A.shape[1]), np.float32) / np.sqrt(A.shape[1])
    lo, up = np.empty((2, 200)), np.empty((2, 200))
    rows = np.arange(200, dtype=np.int64)
    assert kernels.half_bounds(A, rows, V, np.zeros(200, np.float32), lo, up) == 90
    ok = rows[5:80]
    assert kernels.half_bounds(A, ok, V, np.zeros(200, np.float32), lo[:, :75], up[:, :75]) == -1
