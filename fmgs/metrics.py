"""Image quality metrics: PSNR and SSIM (the 11x11, sigma 1.5 Gaussian window of graphdeco 3DGS)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def psnr(img: torch.Tensor, ref: torch.Tensor, max_val: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB of [H,W,C] images (identical images give +inf)."""
    mse = float(torch.mean((img.double() - ref.double()) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(max_val**2 / mse)


def _window(size: int, sigma: float, channels: int, dtype, device) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    g = g / g.sum()
    return (g[:, None] * g[None, :]).expand(channels, 1, size, size).contiguous()


def ssim(img: torch.Tensor, ref: torch.Tensor, size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM of [H,W,C] images in [0,1], differentiable; zero padding at the borders (as graphdeco)."""
    if img.shape != ref.shape or img.ndim != 3:
        raise ValueError(
            f"ssim needs two [H,W,C] images of one shape, got {list(img.shape)}, {list(ref.shape)}"
        )
    c = img.shape[-1]
    x = img.permute(2, 0, 1)[None]
    y = ref.permute(2, 0, 1)[None].to(x)
    w = _window(size, sigma, c, x.dtype, x.device)

    def blur(t):
        return F.conv2d(t, w, padding=size // 2, groups=c)

    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return s.mean()
