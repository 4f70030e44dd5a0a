"""The differentiable CPU path (numba blending forward and backward) against its exact twin, the
reference rasteriser under autograd: outputs, statistics and the gradient of every input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fmgs.render import RasterConfig, rasterize
from tests.helpers.scenes import random_scene

NAMES = ("means", "quats", "scales", "opacities", "features", "background")


def _render_and_grads(sc, backend: str, dtype, config: RasterConfig, seed: int = 0):
    """Outputs and d/d(inputs) of a random linear functional of image, alpha and depth."""
    inputs = {
        "means": sc.means,
        "quats": sc.quats,
        "scales": sc.scales,
        "opacities": sc.opacities,
        "features": sc.features,
        "background": sc.background,
    }
    x = {k: v.to(dtype).clone().requires_grad_(True) for k, v in inputs.items() if v is not None}
    out = rasterize(
        x["means"], x["quats"], x["scales"], x["opacities"], x["features"], sc.camera,
        background=x.get("background"), config=config, backend=backend,
    )  # fmt: skip
    out.means2d.retain_grad()
    g = torch.Generator().manual_seed(seed)
    loss = sum(
        (t * torch.randn(t.shape, generator=g, dtype=torch.float64).to(t.dtype)).sum()
        for t in (out.image, out.alpha, out.depth)
    )
    loss.backward()
    grads = {k: v.grad for k, v in x.items()}
    grads["means2d"] = out.means2d.grad
    return out, grads


def _compare(sc, dtype, rtol, config=RasterConfig(), ref_config=None):
    a, ga = _render_and_grads(sc, "cpu", dtype, config)
    b, gb = _render_and_grads(sc, "reference", dtype, ref_config or config)
    for name in ("image", "alpha", "depth"):
        x, y = getattr(a, name).detach(), getattr(b, name).detach()
        assert x.dtype == y.dtype == dtype
        scale = max(float(y.abs().max()), 1.0)
        assert float((x - y).abs().max()) <= rtol * scale, name
    assert torch.equal(a.n_contrib, b.n_contrib)
    assert torch.allclose(a.weight_sum, b.weight_sum, rtol=1e-12, atol=1e-12)
    assert torch.equal(a.radii, b.radii) and torch.equal(a.visible, b.visible)
    for name in (*NAMES, "means2d"):
        if gb.get(name) is None:
            continue
        x, y = ga[name], gb[name]
        assert x is not None, name
        assert torch.isfinite(x).all(), name
        scale = max(float(y.abs().max()), 1e-12)
        assert float((x - y).abs().max()) <= rtol * scale, (name, float((x - y).abs().max()), scale)
        assert float(y.abs().max()) > 0, f"{name}: the functional must depend on it"


@pytest.mark.parametrize("seed", range(6))
def test_matches_reference_float64(seed):
    sc = random_scene(seed=seed, n=300, d=3, width=37, height=29, focal=30.0, background=True)
    _compare(sc, torch.float64, 1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_matches_reference_float32(seed):
    sc = random_scene(seed=seed, n=300, d=3, width=40, height=30, focal=30.0, background=True)
    _compare(sc, torch.float32, 1e-5)


@pytest.mark.parametrize("tile", [1, 4, 16, 64])
def test_tile_size_does_not_change_the_result(tile):
    sc = random_scene(seed=7, n=200, d=5, width=33, height=21, focal=25.0)
    cfg, ref = RasterConfig(tile_size=tile), RasterConfig(tile_size=8)
    _compare(sc, torch.float64, 1e-9, config=cfg, ref_config=ref)


def test_opaque_stacks_terminate_and_clamp_like_the_reference():
    # Many large, nearly opaque Gaussians: pixels terminate early and alphas hit the 0.99 clamp.
    sc = random_scene(seed=3, n=400, d=3, width=32, height=24, focal=30.0, log_scale=(-1.0, 0.0))
    sc = sc._replace(opacities=torch.where(torch.arange(400) % 2 == 0, 1.0, sc.opacities.double()))
    a, _ = _render_and_grads(sc, "cpu", torch.float64, RasterConfig())
    assert float(a.alpha.max()) > 0.999  # terminated pixels exist
    _compare(sc, torch.float64, 1e-9)


def test_wide_features_and_no_background():
    sc = random_scene(seed=11, n=150, d=40, width=24, height=20, focal=20.0)
    _compare(sc, torch.float64, 1e-9)


def test_gradcheck_float64():
    sc = random_scene(seed=1, n=6, d=3, width=9, height=7, focal=12.0, log_scale=(-1.5, -0.7), spread=0.8)
    sc = sc._replace(opacities=sc.opacities.clamp(0.05, 0.9))
    m0 = sc.means.clone().requires_grad_(True)
    f0 = sc.features.clone().requires_grad_(True)

    def f(m, feat):
        out = rasterize(m, sc.quats, sc.scales, sc.opacities, feat, sc.camera, backend="cpu")
        return out.image, out.alpha, out.depth

    assert torch.autograd.gradcheck(f, (m0, f0), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_empty_and_offscreen_scenes_have_zero_gradients():
    sc = random_scene(seed=2, n=5, d=3, width=8, height=8, focal=10.0)
    m = (sc.means + torch.tensor([0.0, 0.0, -100.0])).requires_grad_(True)  # behind the camera or far off
    f = sc.features.clone().requires_grad_(True)
    bg = torch.ones(3)
    out = rasterize(m, sc.quats, sc.scales, sc.opacities, f, sc.camera, background=bg, backend="cpu")
    out.image.sum().backward()
    assert torch.isfinite(out.image).all()
    assert m.grad is not None and torch.isfinite(m.grad).all()
    empty = rasterize(
        m[:0].detach().requires_grad_(True), sc.quats[:0], sc.scales[:0], sc.opacities[:0],
        f[:0].detach().requires_grad_(True), sc.camera, backend="cpu",
    )  # fmt: skip
    empty.image.sum().backward()
    assert float(empty.image.abs().sum()) == 0


def _uses_numba_blend(t: torch.Tensor) -> bool:
    seen, stack = set(), [t.grad_fn]
    while stack:
        fn = stack.pop()
        if fn is None or fn in seen:
            continue
        seen.add(fn)
        if "_Blend" in fn.name():
            return True
        stack.extend(n for n, _ in fn.next_functions)
    return False


def test_auto_picks_cpu_for_narrow_features_with_gradients():
    sc = random_scene(seed=0, n=20, d=3, width=8, height=8, focal=10.0)
    geom = [t.float() for t in (sc.means, sc.quats, sc.scales, sc.opacities)]
    narrow = sc.features.float().requires_grad_(True)
    assert _uses_numba_blend(rasterize(*geom, narrow, sc.camera).image)
    wide = torch.from_numpy(np.random.default_rng(0).normal(size=(20, 64))).float().requires_grad_(True)
    assert not _uses_numba_blend(rasterize(*geom, wide, sc.camera).image)
    assert _uses_numba_blend(rasterize(*geom, wide, sc.camera, backend="cpu").image)
