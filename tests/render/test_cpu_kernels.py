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


def _boxes(rng, n: int, tiles_x: int, tiles_y: int) -> np.ndarray:
    """Random inclusive tile boxes [n,4] (x0, y0, x1, y1), some one tile, some the whole image."""
    x0, y0 = rng.integers(0, tiles_x, n), rng.integers(0, tiles_y, n)
    x1 = np.minimum(x0 + rng.geometric(0.3, n) - 1, tiles_x - 1)
    y1 = np.minimum(y0 + rng.geometric(0.3, n) - 1, tiles_y - 1)
    box = np.stack([x0, y0, x1, y1], 1).astype(np.int64)
    box[: n // 50] = [0, 0, tiles_x - 1, tiles_y - 1]
    return box


@given(st.integers(0, 2**32 - 1), st.integers(0, 5000), st.integers(1, 9))
def test_parallel_binning_is_the_serial_counting_sort(seed, n, chunks):
    rng = np.random.default_rng(seed)
    tiles_x, tiles_y = int(rng.integers(1, 12)), int(rng.integers(1, 9))
    tbox = _boxes(rng, n + 10, tiles_x, tiles_y)
    order = rng.permutation(n + 10)[:n].astype(np.int64)  # a front-to-back order of some Gaussians
    ids, offsets = k.bin_kernel(order, tbox, tiles_x, tiles_y)
    ids_p, offsets_p = k.bin_kernel_parallel(order, tbox, tiles_x, tiles_y, chunks)
    np.testing.assert_array_equal(offsets_p, offsets)
    np.testing.assert_array_equal(ids_p, ids)  # each tile's list in the same (depth) order


@given(st.integers(0, 2**32 - 1), st.integers(1, 400), st.integers(1, 5000))
def test_tile_batches_cover_the_order_in_bounded_batches(seed, tiles, batch_pairs):
    import fmgs.render.cpu_fast as cf

    rng = np.random.default_rng(seed)
    lens = rng.geometric(0.01, tiles) * (rng.random(tiles) < 0.8)  # some tiles empty
    offsets = np.concatenate([[0], np.cumsum(lens)])
    order = cf.costliest_tiles_first(offsets)
    saved = cf.BATCH_PAIRS
    cf.BATCH_PAIRS = batch_pairs
    try:
        batches = cf.tile_batches(offsets, order)
    finally:
        cf.BATCH_PAIRS = saved
    np.testing.assert_array_equal(np.concatenate(batches), order)
    assert len(batches) == max(cf.TILE_BATCHES, -(-int(lens.sum()) // batch_pairs))
    if len(batches) > cf.TILE_BATCHES:  # cut by pairs: a batch holds at most the cap and one more tile
        for b in batches:
            assert len(b) == 0 or lens[b].sum() <= batch_pairs + lens[b].max()
