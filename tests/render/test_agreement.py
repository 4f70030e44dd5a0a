"""Reference and CPU fast path against the float64 brute force, on hypothesis-generated scenes."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from fmgs.render import RasterConfig, rasterize
from fmgs.render.cpu_fast import project_cpu
from fmgs.render.projection import project
from tests.helpers.brute_force import brute_force_render
from tests.helpers.scenes import random_scene
from tests.helpers.tolerances import assert_close

scene_params = st.fixed_dictionaries(
    {
        "seed": st.integers(0, 2**32 - 1),
        "n": st.integers(1, 48),
        "d": st.sampled_from([1, 3, 5, 16]),
        "width": st.integers(1, 40),
        "height": st.integers(1, 40),
        "focal": st.floats(2.0, 400.0),
        "background": st.booleans(),
        "spread": st.floats(0.1, 3.0),
    }
)


def _check(out, ref, dtype, what):
    assert_close(out.image, ref.image, dtype, f"{what} image")
    assert_close(out.alpha, ref.alpha, dtype, f"{what} alpha")
    assert_close(out.depth, ref.depth, dtype, f"{what} depth")
    # Discrete decisions are float64 in every backend: contributor counts match exactly.
    np.testing.assert_array_equal(out.n_contrib.numpy(), ref.n_contrib, err_msg=f"{what} n_contrib")
    np.testing.assert_allclose(out.weight_sum.numpy(), ref.weight_sum, rtol=1e-9, atol=1e-12)


@given(scene_params, st.sampled_from(["reference", "cpu"]), st.sampled_from([torch.float32, torch.float64]))
def test_backends_match_brute_force(params, backend, dtype):
    sc = random_scene(**params)
    ref = brute_force_render(**sc.brute_args(dtype))
    bg = None if sc.background is None else sc.background.to(dtype)
    out = rasterize(*sc.args(dtype), background=bg, backend=backend)
    assert out.image.dtype == dtype
    _check(out, ref, dtype, backend)


@given(scene_params, st.sampled_from([4, 7, 16, 32]), st.sampled_from([64, 4096, 1 << 22]))
def test_tiles_and_chunks_do_not_change_the_result(params, tile, chunk):
    """Tile size and the reference's memory chunking are implementation details: same output."""
    sc = random_scene(**params)
    ref = brute_force_render(**sc.brute_args(torch.float64))
    cfg = RasterConfig(tile_size=tile, chunk_elems=chunk)
    for backend in ("reference", "cpu"):
        out = rasterize(*sc.args(torch.float64), background=sc.background, config=cfg, backend=backend)
        _check(out, ref, torch.float64, f"{backend} tile={tile} chunk={chunk}")


@given(scene_params, st.sampled_from([torch.float32, torch.float64]))
def test_cpu_projection_twin(params, dtype):
    """The numba projection kernel and the PyTorch projection agree (both widen inputs to float64)."""
    sc = random_scene(**params)
    m, q, s, o, _, cam = sc.args(dtype)
    cfg = RasterConfig()
    a = project(m, q, s, o, cam, cfg)
    b = project_cpu(m, q, s, o, cam, cfg)
    vis = a.visible.numpy()
    np.testing.assert_array_equal(vis, b["visible"])
    np.testing.assert_array_equal(a.radii.numpy(), b["radii"])
    np.testing.assert_array_equal(a.bbox.numpy()[vis], b["bbox"][vis])
    np.testing.assert_allclose(a.means2d.numpy()[vis], b["means2d"][vis], rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(a.conics.numpy()[vis], b["conics"][vis], rtol=1e-10, atol=1e-300)


@given(scene_params)
def test_cpu_matches_reference(params):
    sc = random_scene(**params)
    a = rasterize(*sc.args(torch.float32), background=sc.background, backend="reference")
    b = rasterize(*sc.args(torch.float32), background=sc.background, backend="cpu")
    assert_close(b.image, a.image, torch.float32, "cpu vs reference")
    np.testing.assert_array_equal(a.n_contrib.numpy(), b.n_contrib.numpy())
    np.testing.assert_array_equal(a.radii.numpy(), b.radii.numpy())
    np.testing.assert_array_equal(a.visible.numpy(), b.visible.numpy())


@pytest.mark.parametrize("d", [1, 3, 5, 32, 512, 896])
def test_channel_counts(d):
    """Every channel count from 1 to 896 (512 CLIP + 384 DINO) renders identically in both backends."""
    sc = random_scene(seed=d, n=30, d=d, width=24, height=20, focal=30.0, background=True)
    ref = brute_force_render(**sc.brute_args(torch.float32))
    for backend in ("reference", "cpu"):
        out = rasterize(*sc.args(torch.float32), background=sc.background.float(), backend=backend)
        assert out.image.shape == (20, 24, d)
        assert_close(out.image, ref.image, torch.float32, f"{backend} D={d}")
