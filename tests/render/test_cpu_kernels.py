"""The CPU backend's helper kernels against their numpy twins."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from numba import njit

from fmgs.render import cpu_kernels as k
from fmgs.render.types import RasterConfig


@given(st.integers(0, 2**32 - 1), st.integers(0, 3000), st.sampled_from(["unique", "ties", "spread"]))
def test_radix_argsort_is_numpys_stable_argsort(seed, n, kind):
    rng = np.random.default_rng(seed)
    if kind == "ties":
        keys = rng.integers(1, 5, n).astype(np.float64) * 0.1  # many equal keys: order must be stable
    elif kind == "spread":
        keys = np.exp(rng.uniform(-700, 700, n))  # every exponent range
    else:
        keys = rng.uniform(0.01, 100.0, n)
    np.testing.assert_array_equal(k.stable_argsort_positive(keys), np.argsort(keys, kind="stable"))


@njit
def _eval(x, table):
    out = np.empty_like(x)
    for i in range(x.shape[0]):
        out[i] = k.exp_neg_table(x[i], table)
    return out


@pytest.mark.parametrize("alpha_min", [RasterConfig().alpha_min, 1e-6, 0.1])
def test_table_exp_within_two_ulp(alpha_min):
    table = k.exp_table(alpha_min)
    x_end = -(len(table) - 1) / 256.0
    x = np.concatenate(
        [
            -np.random.default_rng(0).uniform(0, -x_end, 200_000),
            [0.0, -0.0, -1e-300, -5e-324, x_end],
            -np.arange(len(table)) / 256.0,  # the table's nodes
            -np.arange(len(table)) / 256.0 - 1e-12,  # just past each node
        ]
    )
    out, exact = _eval(x, table), np.exp(x)
    assert np.max(np.abs(out - exact) / np.spacing(exact)) <= 2
    assert _eval(np.array([0.0]), table)[0] == 1.0  # exact at zero: the 0.99 clamp stays exact
    beyond = np.array([x_end - 5.0, -700.0])  # past the table: math.exp
    np.testing.assert_allclose(_eval(beyond, table), np.exp(beyond), rtol=1e-15)
