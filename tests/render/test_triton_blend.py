"""The triton backend (fmgs/render/triton_blend.py) against the float64 brute force.

Without a GPU the kernel runs in Triton's interpreter (tests/conftest.py sets TRITON_INTERPRET=1 when
no CUDA device is visible), so CI checks its logic: the rule's decisions, the channel and pixel blocks,
padding pixels and channels, the carried transmittance. Its speed and its compiled float behaviour are
checked on a GPU (tests/cuda/test_triton_cuda.py, benchmarks/gpu.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fmgs.errors import ValidationError
from fmgs.render import RasterConfig, rasterize
from tests.helpers.brute_force import brute_force_render
from tests.helpers.scenes import random_scene
from tests.helpers.tolerances import RTOL, assert_close
from tests.render.test_stiff import _exact_alpha_image, _rand_quats, _scene, stacked_layers

triton = pytest.importorskip("triton", reason="the triton backend needs Triton (in requirements/test.txt)")
if torch.cuda.is_available():
    pytest.skip(
        "a CUDA device is visible: tests/cuda/test_triton_cuda.py checks the compiled kernel",
        allow_module_level=True,
    )

from fmgs.render.projection import project  # noqa: E402
from fmgs.render.triton_blend import BlendTuning, project_triton, rasterize_triton  # noqa: E402

# The default launch; a small one: 64-pixel blocks (four programs per 16x16 tile), 16 channels per
# program, float32 alpha from tile-relative offsets, plain float32 products; and the weights-once path
# (tile extents, then the weights into a buffer, then multiplied by each block of channels).
TUNINGS = {
    "default": BlendTuning(),
    "small": BlendTuning(64, 16, 16, False, "ieee", 4),
    "weights_once": BlendTuning(128, 32, 16, True, "tf32x3", 8, stages=3, weights_once=1),
}


def _check(sc, tuning: BlendTuning, dtype=torch.float32, config: RasterConfig | None = None):
    ref = brute_force_render(**sc.brute_args(dtype))
    bg = None if sc.background is None else sc.background.to(dtype)
    out = rasterize_triton(*sc.args(dtype), background=bg, config=config or RasterConfig(), tuning=tuning)
    for name in ("image", "alpha", "depth"):
        got = getattr(out, name)
        assert got.dtype == dtype and torch.isfinite(got).all(), name
        # Features meet the weights in float32 whatever their dtype: float32's tolerance at most.
        assert_close(got, getattr(ref, name), max(dtype, torch.float32, key=lambda d: RTOL[d]), name)
    return ref, out


@pytest.mark.parametrize("tuning", TUNINGS)
@pytest.mark.parametrize("d", [1, 5, 70])
def test_random_scenes_match_the_brute_force(tuning, d):
    # 70 channels: two 64-channel programs (five 16-channel ones), the last partly padding.
    sc = random_scene(seed=d, n=120, d=d, width=37, height=21, focal=30.0, background=True)
    _check(sc, TUNINGS[tuning])


@pytest.mark.parametrize("tile", [8, 12])
def test_other_tile_sizes(tile):
    # 12x12 tiles have 144 pixels: a 256-pixel block with 112 padding pixels.
    sc = random_scene(seed=tile, n=80, d=3, width=29, height=19, focal=25.0)
    _check(sc, BlendTuning(), config=RasterConfig(tile_size=tile))


@pytest.mark.parametrize("tuning", ["default", "weights_once"])
@pytest.mark.parametrize("opacity", [1 - 1e-7, 0.02])
def test_ten_thousand_stacked_layers(opacity, tuning):
    """Early termination over many list steps: alpha clamps to alpha_max, T crosses 1e-4 mid-step."""
    sc = stacked_layers(opacity)
    _check(sc, TUNINGS[tuning])


def test_needle_seen_far_from_its_centre():
    # As tests/render/test_stiff.py's needle: the centre 1e5 px off-image, reaching in at an angle.
    W = H = 32
    focal, depth, theta, distance = 1024.0, 8.0, 0.3, 1e5
    u0, v0 = W / 2 - distance * math.cos(theta), H / 2 - distance * math.sin(theta)
    sc = _scene(
        [[(u0 - W / 2) / focal * depth, (v0 - H / 2) / focal * depth, depth]],
        [[math.cos(theta / 2), 0, 0, math.sin(theta / 2)]],
        [[distance / 2.5 * depth / focal, 1e-3, 1e-3]],
        [0.9],
        feats=[[1.0]],
        width=W,
        height=H,
        focal=focal,
    )
    _, out = _check(sc, BlendTuning(), dtype=torch.float64)
    exact = _exact_alpha_image(sc, RasterConfig())  # exact rationals; NaN where rounding may decide
    lit = exact > 0
    assert lit.sum() > 50
    np.testing.assert_array_equal(out.alpha.numpy()[~np.isnan(exact) & ~lit], 0.0)
    rel = np.abs(out.alpha.numpy()[lit] - exact[lit]) / exact[lit]
    assert rel.max() <= 2e-15 * distance  # float64 alpha, the reference's bound


def test_stiff_scenes():
    rng = np.random.default_rng(2)
    cases = [
        # opacity extremes: 0, 1 (clamped to alpha_max), 1e-30, 1 - 1e-16
        _scene(rng.normal(size=(8, 3)) * 0.3 + [0, 0, 3], _rand_quats(8, 1), np.full((8, 3), 0.2),
               [0, 1, 1, 0, 1e-30, 1 - 1e-16, 0.5, 1]),
        # the camera inside a Gaussian, one behind it
        _scene([[0.0, 0.0, 0.5], [0.1, 0.0, -0.3], [0.0, 0.2, 3.0]], _rand_quats(3, 6),
               [[5.0, 4.0, 6.0], [5.0, 5.0, 5.0], [0.3, 0.3, 0.3]], [0.5, 0.9, 0.8]),
        # sub-pixel Gaussians (eps2d dilation dominates)
        _scene(np.c_[rng.uniform(-1, 1, (20, 2)), rng.uniform(3, 6, 20)], _rand_quats(20, 2),
               np.full((20, 3), 1e-5), np.full(20, 0.95)),
        # a Gaussian covering the whole image in front of a small one
        _scene([[0.0, 0.0, 4.0], [0.3, -0.2, 5.0]], _rand_quats(2, 3), [[100.0, 80.0, 50.0], [0.2, 0.2, 0.2]],
               [0.6, 0.9]),
    ]  # fmt: skip
    for sc in cases:
        for tuning in TUNINGS.values():
            _check(sc, tuning)


@pytest.mark.parametrize("size", [(1, 1), (1, 37), (23, 1)])
def test_degenerate_image_sizes(size):
    w, h = size
    sc = random_scene(seed=w * 100 + h, n=25, d=4, width=w, height=h, focal=3.0, background=True)
    _check(sc, BlendTuning())


def test_nothing_in_view_gives_the_background():
    sc = _scene([[0, 0, -3.0], [0, 0, -1.0]], _rand_quats(2, 7), np.full((2, 3), 0.3), [0.9, 0.9])
    sc = sc._replace(background=torch.tensor([0.25, -1.0, 3.0], dtype=torch.float64))
    _, out = _check(sc, BlendTuning())
    assert (out.alpha == 0).all()
    assert (out.image == torch.tensor([0.25, -1.0, 3.0])).all()


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_features_come_back_in_their_dtype(dtype):
    sc = random_scene(seed=11, n=60, d=20, width=24, height=20, focal=20.0)
    out = rasterize_triton(*sc.args(torch.float32)[:4], sc.features.to(dtype), sc.camera)
    assert out.image.dtype == dtype
    # The blend of the half features, rounded once to the half dtype at the end.
    ref = rasterize(
        *sc.args(torch.float64)[:4], sc.features.to(dtype).double(), sc.camera, backend="reference"
    )
    assert_close(out.image, ref.image, dtype, "image")


def test_rasterize_dispatches_and_refuses_gradients():
    sc = random_scene(seed=3, n=40, d=6, width=20, height=16, focal=18.0)
    a = rasterize(*sc.args(), backend="triton")
    b = rasterize_triton(*sc.args())
    assert torch.equal(a.image, b.image) and torch.equal(a.alpha, b.alpha)
    feats = sc.features.float().requires_grad_(True)
    with pytest.raises(ValidationError, match="without gradients"):
        rasterize(*sc.args()[:4], feats, sc.camera, backend="triton")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_projection_kernel_is_projects_twin(dtype):
    """project_triton does projection.project's float64 arithmetic: the same culling, boxes and radii, and
    the same centres, depths and conics up to the order of a few sums (1e-12 relative)."""
    rng = np.random.default_rng(5)
    n = 40
    means = np.r_[rng.normal(size=(n, 3)) * 0.5 + [0, 0, 3], [[0, 0, 0.125], [0, 0, -1.0], [1e30, 0, 1e30]]]
    quats = np.r_[_rand_quats(n, 3), [[1e-300, 0, 0, 1e-300], [0, 1, 0, 0], [1, 1, 1, 1]]]
    scales = np.r_[
        np.abs(rng.normal(size=(n, 3))) * [0.3, 1e-6, 1e-3], [[0.1] * 3, [0.1] * 3, [1e20, 1, 1e-20]]
    ]
    opac = np.r_[rng.uniform(0, 1, n), [1.0, 0.5, 1e-30]]
    scenes = [
        random_scene(seed=9, n=300, d=1, width=53, height=29, focal=40.0),
        # needles, means on and behind the near plane, huge and tiny values, denormal quats, opacity extremes
        _scene(means, quats, scales, opac, near=0.125),
    ]
    for sc in scenes:
        args = [
            t.to(dtype) if t.dtype == torch.float64 and dtype == torch.float32 else t
            for t in sc.args(dtype)[:4]
        ]
        a = project(*args, sc.camera, RasterConfig())
        b = project_triton(*args, sc.camera, RasterConfig())
        for name in ("radii", "bbox", "visible"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
        for name in ("means2d", "depths", "conics", "opacities"):
            x, y = getattr(a, name)[a.visible], getattr(b, name)[a.visible]
            assert torch.isfinite(y).all(), name
            assert float(((x - y).abs() / x.abs().clamp_min(1e-300)).max()) <= 1e-12, name


def test_weights_once_equals_the_single_pass():
    """Both paths form the same float32 weights and the same products in the same order: equal images."""
    sc = random_scene(seed=21, n=200, d=50, width=40, height=33, focal=30.0, background=True)
    single = rasterize_triton(
        *sc.args(), sc.background.float(), tuning=BlendTuning(block_channels=16, weights_once=0)
    )
    once = rasterize_triton(
        *sc.args(), sc.background.float(), tuning=BlendTuning(block_channels=16, weights_once=1)
    )
    for name in ("image", "alpha", "depth"):
        assert torch.equal(getattr(single, name), getattr(once, name)), name
