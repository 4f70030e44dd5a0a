"""Image metrics: the separable SSIM against its full-window twin, values and gradients."""

from __future__ import annotations

import math

import pytest
import torch

from fmgs.metrics import psnr, ssim, ssim_reference
from tests.helpers.tolerances import rel_err

# Relative error (max |a - b| / max |b|) between the separable and full-window SSIM. Values differ by
# rounding only; float32 gradients of near-identical images lose more because the variance is taken
# as E[x^2] - E[x]^2 in both (measured worst over these cases: 5.5e-7 values, 3.0e-5 gradients in
# float32; 1.3e-15 and 5.7e-14 in float64).
TOL = {torch.float32: {"value": 1e-5, "grad": 1e-4}, torch.float64: {"value": 1e-12, "grad": 1e-12}}

SHAPES = [(1, 1, 3), (5, 7, 3), (7, 5, 1), (23, 2, 4), (96, 128, 3)]


def _pair(shape: tuple[int, ...], dtype: torch.dtype, near: bool) -> tuple[torch.Tensor, torch.Tensor]:
    img = torch.rand(shape, dtype=dtype)
    # near: a render close to its target, where SSIM is near 1 and the variances cancel the most.
    ref = (
        (img + 0.01 * torch.randn(shape, dtype=dtype)).clamp(0, 1) if near else torch.rand(shape, dtype=dtype)
    )
    return img.requires_grad_(), ref.requires_grad_()


def _compare(fn, img: torch.Tensor, ref: torch.Tensor) -> tuple[float, float]:
    """Relative error of ``fn`` against ssim_reference: (value, worst gradient of img and ref)."""
    a, b = fn(img, ref), ssim_reference(img, ref)
    ga, gb = torch.autograd.grad(a, (img, ref)), torch.autograd.grad(b, (img, ref))
    return rel_err(a, b), max(rel_err(x, y) for x, y in zip(ga, gb, strict=True))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: "x".join(map(str, s)))
@pytest.mark.parametrize("near", [False, True], ids=["random", "near"])
def test_separable_ssim_equals_full_window(shape, dtype, near):
    img, ref = _pair(shape, dtype, near)
    value, grad = _compare(ssim, img, ref)
    assert value <= TOL[dtype]["value"], f"value: relative error {value:.2e}"
    assert grad <= TOL[dtype]["grad"], f"gradient: relative error {grad:.2e}"


def test_comparison_catches_a_slightly_wrong_window():
    """The float64 tolerance is tight enough to see a window one part in a million too wide."""
    img, ref = _pair((23, 17, 3), torch.float64, near=False)
    value, grad = _compare(lambda a, b: ssim(a, b, sigma=1.5 * (1 + 1e-6)), img, ref)
    assert value > TOL[torch.float64]["value"] and grad > TOL[torch.float64]["grad"]


def test_ssim_of_an_image_with_itself_is_one():
    img = torch.rand(9, 13, 3, dtype=torch.float64)
    assert float(ssim(img, img)) == pytest.approx(1.0, abs=1e-12)
    assert psnr(img, img) == math.inf


def test_ssim_refuses_mismatched_shapes():
    with pytest.raises(ValueError, match=r"ssim needs two \[H,W,C\] images"):
        ssim(torch.rand(4, 4, 3), torch.rand(4, 5, 3))
