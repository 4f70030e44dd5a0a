"""Image quality metrics: PSNR and SSIM (the 11x11, sigma 1.5 Gaussian window of graphdeco 3DGS)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def psnr(img: torch.Tensor, ref: torch.Tensor, max_val: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB of [H,W,C] images (identical images give +inf)."""
    mse = float(torch.mean((img.double() - ref.double()) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(max_val**2 / mse)


def _gauss(size: int, sigma: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """The normalised 1D Gaussian [size]; the 2D window is its outer product with itself."""
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def _check(img: torch.Tensor, ref: torch.Tensor) -> None:
    if img.shape != ref.shape or img.ndim != 3:
        raise ValueError(
            f"ssim needs two [H,W,C] images of one shape, got {list(img.shape)}, {list(ref.shape)}"
        )


def _ssim_map(mx, my, xx, yy, xy) -> torch.Tensor:
    sxx, syy, sxy = xx - mx * mx, yy - my * my, xy - mx * my
    c1, c2 = 0.01**2, 0.03**2
    return ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))


def ssim(img: torch.Tensor, ref: torch.Tensor, size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM of [H,W,C] images in [0,1], differentiable; zero padding at the borders (as graphdeco).

    The Gaussian window is separable, so the blur is a 1D conv down the columns then one along the
    rows (2*size taps a pixel instead of size**2), and the five blurred maps go through one grouped
    conv. Equal to ``ssim_reference`` (the full-window twin) up to float rounding, gradients too.
    """
    _check(img, ref)
    c = img.shape[-1]
    x = img.permute(2, 0, 1)[None]
    y = ref.permute(2, 0, 1)[None].to(x)
    g = _gauss(size, sigma, x.dtype, x.device)
    # Zero padding separates too: a row of the padded image outside the border is all zeros.
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    stack = F.conv2d(
        stack, g.view(1, 1, size, 1).expand(5 * c, 1, size, 1), padding=(size // 2, 0), groups=5 * c
    )
    stack = F.conv2d(
        stack, g.view(1, 1, 1, size).expand(5 * c, 1, 1, size), padding=(0, size // 2), groups=5 * c
    )
    return _ssim_map(*stack.split(c, dim=1)).mean()


def ssim_reference(img: torch.Tensor, ref: torch.Tensor, size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """``ssim`` with the full size x size window conv: the slow, obvious twin the tests compare to."""
    _check(img, ref)
    c = img.shape[-1]
    x = img.permute(2, 0, 1)[None]
    y = ref.permute(2, 0, 1)[None].to(x)
    g = _gauss(size, sigma, x.dtype, x.device)
    w = (g[:, None] * g[None, :]).expand(c, 1, size, size)

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(t, w, padding=size // 2, groups=c)

    return _ssim_map(blur(x), blur(y), blur(x * x), blur(y * y), blur(x * y)).mean()
