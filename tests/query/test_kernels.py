"""The float16 kernels of the text query against their float64 twin: exact decoding of every bit
pattern, the float32 pass within its stated rounding bound, the float64 pass equal to the ordered sum."""

from __future__ import annotations

import numpy as np
import pytest

from fmgs.query import kernels
from fmgs.query.reference import (
    at_least_reference,
    float_dots_reference,
    half_decode_reference,
    half_dots_reference,
    int8_upper_reference,
    tier2_bounds_reference,
)


def test_every_float16_bit_pattern_decodes_exactly():
    allbits = np.arange(65536, dtype=np.uint32).astype(np.uint16).reshape(256, 256)
    out = np.empty((256, 256), np.float32)
    kernels.half_decode(allbits, out)
    ref = half_decode_reference(allbits)
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
    ref = half_dots_reference(A, rows, V)
    absref = np.abs(half_decode_reference(A[rows]).astype(np.float64)) @ np.abs(V.astype(np.float64)).T
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
    assert np.array_equal(out, half_dots_reference(A, rows, V))
    # Every group size (rows are summed four at a time, 64 per block) and text count; repeated rows.
    for m in (1, 2, 3, 5, 63, 64, 65, 130):
        r = np.random.default_rng(m).integers(0, len(A), m).astype(np.int64)
        for n in (1, 3):
            o = np.empty((m, n))
            kernels.half_dots64(A, r, V[:1].repeat(n, 0) * np.arange(1, n + 1)[:, None], o)
            assert np.array_equal(
                o, half_dots_reference(A, r, V[:1].repeat(n, 0) * np.arange(1, n + 1)[:, None])
            )


def test_float32_rows_float64_pass_equals_the_ordered_sum():
    rng = np.random.default_rng(5)
    A = (rng.standard_normal((200, 67)) * np.logspace(-30, 30, 67)).astype(np.float32)
    A[3] = np.finfo(np.float32).max
    V = rng.standard_normal((3, 67)).astype(np.float32).astype(np.float64)
    for m in (1, 2, 7, 200):
        r = rng.integers(0, len(A), m).astype(np.int64)
        out = np.empty((m, 3))
        kernels.float_dots64(A, r, V, out)
        assert np.array_equal(out, float_dots_reference(A, r, V))


def test_float64_pass_reads_damaged_values_as_infinite():
    """inf, -inf and NaN read as +inf (as the twin decodes them), so a damaged row is never finite."""
    A = _rows_with_extremes(M=12)
    for row, bits in ((2, 0x7C00), (5, 0xFC00), (7, 0x7E00), (9, 0xFE01)):
        A[row, 3] = bits
    V = np.ones((1, A.shape[1])) / A.shape[1]
    rows = np.arange(12, dtype=np.int64)
    out = np.empty((12, 1))
    kernels.half_dots64(A, rows, V, out)
    assert np.array_equal(out, half_dots_reference(A, rows, V), equal_nan=True)
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
    exact = half_dots_reference(A, rows, V).T - shift[rows].astype(np.float64)[None]
    assert np.all(lo <= exact) and np.all(exact <= up)
    f = half_decode_reference(A[rows]).astype(np.float64)
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


def _codes_and_texts(rng, M: int, r: int, n: int):
    """Int8 codes spanning their range (extremes included) and text weights of mixed scales per text (a
    transposing sum that put a text's total in another's lane would be far off)."""
    A = rng.integers(-127, 128, (M, r), dtype=np.int8)
    A[0], A[1] = 127, -127
    W = (rng.standard_normal((n, r)) * np.geomspace(1e-3, 10, n)[:, None]).astype(np.float32)
    return A, W


def _sum_tolerance(A: np.ndarray, W: np.ndarray, *terms: np.ndarray) -> np.ndarray:
    """[n,M] bound on a float32 sum of r products in any order plus a few float32 terms, fused or not."""
    mag = np.abs(A.astype(np.float64)) @ np.abs(W.astype(np.float64)).T
    return ((A.shape[1] + 8) * 2.0**-24 * (mag.T + sum(np.abs(t) for t in terms))) + 1e-30


def _with_guard(n: int, m: int, dtype) -> tuple[np.ndarray, np.ndarray]:
    """An [n,m] output of NaN with four guard rows after it in the same buffer (a kernel writing a padded
    text's row would fill them)."""
    big = np.full((n + 4, m), np.nan, dtype)
    return big[:n], big[n:]


@pytest.mark.parametrize("r", [16, 64, 40])  # multiples of 16 take fmgs.query.simd's sums, 40 the loops
@pytest.mark.parametrize("n", [1, 2, 3, 4, 6, 7, 8, 13, 16])
@pytest.mark.parametrize("padded", [False, True])  # kernels.pad_texts: zero weight rows past n
def test_first_tier_upper_bounds_match_their_twin(r, n, padded):
    rng = np.random.default_rng(r * 100 + n)
    M = 700
    A, W = _codes_and_texts(rng, M, r, n)
    shift = rng.standard_normal(M).astype(np.float32)
    err, res = rng.random(M).astype(np.float32), rng.random(M).astype(np.float32)
    wn, vn = rng.random(n).astype(np.float32), rng.random(n).astype(np.float32)
    out, guard = _with_guard(n, M, np.float32)
    Wk = kernels.pad_texts(W)[0] if padded else W
    assert len(Wk) == (n + 4 - n % 4 if padded and n % 4 >= 2 and n != 2 else n)
    kernels.int8_upper(A, Wk, shift, err, res, wn, vn, np.float32(1e-6), out)
    assert np.isnan(guard).all()
    ref = int8_upper_reference(A, W, shift, err, res, wn, vn, 1e-6)
    ew, rv = err.astype(np.float64)[None] * wn[:, None], res.astype(np.float64)[None] * vn[:, None]
    tol = _sum_tolerance(A, W, shift[None], ew, rv)
    assert np.all(np.abs(out - ref) <= tol)


# (first tier, second tier's head, its tail): (64, 40, 0) and (64, 128, 40) take the loops; a tail of 0
# is a second tier stored whole.
@pytest.mark.parametrize(
    "ranks", [(64, 192, 0), (16, 32, 0), (64, 40, 0), (64, 128, 64), (16, 16, 32), (64, 128, 40)]
)
@pytest.mark.parametrize("n", [1, 2, 3, 4, 7, 8, 12, 17])
@pytest.mark.parametrize("padded", [False, True])
def test_second_tier_kernels_match_their_twin(ranks, n, padded):
    rng = np.random.default_rng(ranks[1] * 100 + ranks[2] * 7 + n)
    M = 600
    A1, W1 = _codes_and_texts(rng, M, ranks[0], n)
    A2, W2 = _codes_and_texts(rng, M, ranks[1], n)
    A3, W3 = _codes_and_texts(rng, M, ranks[2], n)
    shift = rng.standard_normal(M).astype(np.float32)
    err1 = rng.random(M).astype(np.float32)
    bounds2 = rng.random((M, 2)).astype(np.float32)
    wn1, wn2, vn2 = (rng.random(n) for _ in range(3))
    picked = rng.choice(np.arange(2, M - 1), 200, replace=False)
    rows = np.concatenate([[M - 1, 0, 1], picked]).astype(np.int64)
    (lo, lo_guard), (up, up_guard) = _with_guard(n, len(rows), float), _with_guard(n, len(rows), float)
    args = (shift, err1, bounds2, wn1, wn2, vn2, 1e-6)
    Wk = kernels.pad_texts(W1, W2, W3) if padded else (W1, W2, W3)
    tiers = [x for pair in zip((A1, A2, A3), Wk, strict=True) for x in pair]
    kernels.tier2_bounds(*tiers, rows, *args, lo, up)
    assert np.isnan(lo_guard).all() and np.isnan(up_guard).all()
    rlo, rup = tier2_bounds_reference(A1, W1, A2, W2, A3, W3, rows, *args)
    A, W = np.concatenate([A1, A2, A3], 1), np.concatenate([W1, W2, W3], 1)
    tol = _sum_tolerance(A, W)
    assert np.all(np.abs(lo - rlo) <= tol[:, rows]) and np.all(np.abs(up - rup) <= tol[:, rows])
    every = np.arange(M, dtype=np.int64)
    up32, guard = _with_guard(n, M, np.float32)
    kernels.tier2_upper(*tiers, *args, up32)
    assert np.isnan(guard).all()
    _, rup_all = tier2_bounds_reference(A1, W1, A2, W2, A3, W3, every, *args)
    assert np.all(up32 >= rup_all - tol)  # rounded up: never below the sum's own error
    assert np.all(up32 - rup_all <= tol + np.abs(rup_all) * 2.0**-21)


def test_at_least_matches_flatnonzero_and_says_when_its_buffer_is_short():
    rng = np.random.default_rng(5)
    for m in (0, 7, 16, 1000, 4099):
        x = rng.standard_normal(m).astype(np.float32)
        x[::13] = np.nan  # never selected
        for cut in (-np.inf, -0.5, 0.0, 1.5, np.inf):
            want = at_least_reference(x, cut)
            out = np.empty(m + kernels.LANES, np.int64)
            got = kernels.at_least(x, np.float32(cut), out)
            assert got == len(want) and np.array_equal(out[:got], want)
            if len(want) > kernels.LANES:  # a buffer too short for them: -1, not a partial answer
                short = np.empty(len(want) - 1, np.int64)
                assert kernels.at_least(x, np.float32(cut), short) == -1
