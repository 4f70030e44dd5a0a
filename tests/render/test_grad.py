"""Gradients of the reference rasteriser: gradcheck in float64, finite in float32."""

from __future__ import annotations

import pytest
import torch

from fmgs.render import rasterize
from tests.helpers.scenes import random_scene


def _scene(seed: int):
    # Opacities kept below the 0.99 clamp: min() is not differentiable at the kink.
    sc = random_scene(
        seed=seed,
        n=6,
        d=3,
        width=9,
        height=7,
        focal=12.0,
        log_scale=(-1.5, -0.7),
        background=True,
        spread=0.8,
    )
    return sc._replace(opacities=sc.opacities.clamp(0.05, 0.9))


# Seed 0 in the fast tier; the other scenes, a few seconds each (gradcheck's Jacobians), in the slow one.
@pytest.mark.parametrize(
    "seed", [0, pytest.param(1, marks=pytest.mark.slow), pytest.param(2, marks=pytest.mark.slow)]
)
@pytest.mark.parametrize("wrt", ["means", "quats", "scales", "opacities", "features", "background"])
def test_gradcheck_reference_float64(seed, wrt):
    sc = _scene(seed)
    inputs = dict(
        means=sc.means,
        quats=sc.quats,
        scales=sc.scales,
        opacities=sc.opacities,
        features=sc.features,
        background=sc.background,
    )
    x = inputs[wrt].clone().requires_grad_(True)

    def f(x):
        args = dict(inputs, **{wrt: x})
        out = rasterize(
            args["means"],
            args["quats"],
            args["scales"],
            args["opacities"],
            args["features"],
            sc.camera,
            background=args["background"],
            backend="reference",
        )
        return out.image, out.alpha, out.depth

    # Non-trivial: the render must depend on x.
    with torch.no_grad():
        base = f(x)[0]
        assert base.abs().max() > 0
    assert torch.autograd.gradcheck(f, (x,), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_gradients_finite_float32_and_match_float64():
    """A random cotangent pulled back in float32 agrees with float64 (mixed-precision backward)."""
    sc = random_scene(seed=7, n=40, d=8, width=32, height=24, focal=30.0, background=True)
    grads = {}
    for dt in (torch.float32, torch.float64):
        leaves = [t.to(dt).clone().requires_grad_(True) for t in (sc.means, sc.quats, sc.scales, sc.features)]
        m, q, s, f = leaves
        out = rasterize(m, q, s, sc.opacities.to(dt).clamp(0, 0.9), f, sc.camera, backend="reference")
        g = torch.Generator().manual_seed(3)
        cot = torch.randn(out.image.shape, generator=g, dtype=torch.float64).to(dt)
        (out.image * cot).sum().backward()
        grads[dt] = [t.grad for t in leaves]
    for g32, g64 in zip(grads[torch.float32], grads[torch.float64], strict=True):
        assert torch.isfinite(g32).all()
        err = (g32.double() - g64).abs().max() / g64.abs().max()
        assert err < 1e-4, err


def test_means2d_gradient_is_view_space_gradient():
    """out.means2d is the tensor the image is built from, so retain_grad gives view-space gradients."""
    sc = random_scene(seed=3, n=10, d=3, width=16, height=16, focal=20.0)
    m = sc.means.clone().requires_grad_(True)
    out = rasterize(m, sc.quats, sc.scales, sc.opacities, sc.features, sc.camera, backend="reference")
    out.means2d.retain_grad()
    out.image.sum().backward()
    g = out.means2d.grad
    assert g is not None and g.shape == (10, 2)
    assert torch.isfinite(g).all() and g[out.visible].abs().sum() > 0
    assert (g[~out.visible] == 0).all()


@pytest.mark.parametrize("backend", ["reference", "cpu"])
@pytest.mark.parametrize("shift", [-100.0, None])  # every mean behind the camera; no Gaussian at all
def test_a_view_that_sees_nothing_gives_zero_gradients(backend, shift):
    """A training step on a view no Gaussian reaches is a zero gradient, not a backward() that raises."""
    sc = random_scene(seed=2, n=5, d=3, width=8, height=8, focal=10.0)
    pick = slice(None) if shift is not None else slice(0)
    move = torch.tensor([0.0, 0.0, shift or 0.0])
    leaves = [
        t[pick].clone().requires_grad_(True)
        for t in (sc.means + move, sc.quats, sc.scales, sc.opacities, sc.features)
    ]
    bg = torch.full((3,), 0.25)
    out = rasterize(*leaves, sc.camera, background=bg, backend=backend)
    assert torch.equal(out.image, bg.expand(8, 8, 3)) and (out.alpha == 0).all()
    (out.image.sum() + out.alpha.sum() + out.depth.sum()).backward()
    for t in leaves:
        assert t.grad is not None and (t.grad == 0).all()
