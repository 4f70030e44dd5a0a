"""Rasteriser configuration and typed outputs shared by every backend."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch


@dataclass(frozen=True)
class RasterConfig:
    """The rendering rule every backend implements (graphdeco 3DGS semantics)."""

    alpha_min: float = 1.0 / 255.0
    """A Gaussian is skipped at a pixel where its alpha is below this."""
    alpha_max: float = 0.99
    """Alpha is clamped to this, so one Gaussian never makes a pixel fully opaque."""
    transmittance_min: float = 1e-4
    """A pixel stops before the Gaussian that would bring its transmittance below this."""
    eps2d: float = 0.3
    """Low-pass dilation (pixels^2) added to the diagonal of every 2D covariance."""
    fov_clip: float = 0.3
    """The EWA Jacobian clamps x/z, y/z to the image's field of view plus this fraction of it."""
    tile_size: int = 16
    """Tile edge in pixels for binning Gaussians."""
    chunk_elems: int = 1 << 20
    """Reference path: pixel x Gaussian (x channel) elements evaluated at once; bounds memory."""

    def __post_init__(self) -> None:
        if not 0 < self.alpha_min < self.alpha_max < 1:
            raise ValueError("need 0 < alpha_min < alpha_max < 1")
        if not 0 < self.transmittance_min < 1:
            raise ValueError("need 0 < transmittance_min < 1")
        if not (0 < self.eps2d < math.inf) or self.tile_size < 1 or self.chunk_elems < 1:
            raise ValueError("eps2d (finite), tile_size and chunk_elems must be positive")
        if not (0 <= self.fov_clip < math.inf):
            raise ValueError(f"fov_clip must be finite and >= 0, got {self.fov_clip}")


class Projection(NamedTuple):
    """Per-Gaussian screen-space quantities (float64), for all N Gaussians."""

    means2d: torch.Tensor
    """[N,2] projected centres in pixels (x, y); the pixel (i, j) centre is (j+0.5, i+0.5)."""
    depths: torch.Tensor
    """[N] camera-space z of the means."""
    conics: torch.Tensor
    """[N,3] (A, r, e): the inverse dilated 2D covariance [[a, b], [b, c]] in completed-square form,
    power = A (dx + r dy)^2 + e dy^2 with A = c / det, r = -b / c, e = 1 / c. Algebraically the conic
    A dx^2 + 2 A r dx dy + (A r^2 + e) dy^2, but without its cancellation: for a needle seen far from
    its centre the conic's terms are ~1e10 times the power, and even correctly rounded conic entries
    lose that many digits."""
    opacities: torch.Tensor
    """[N] opacities in [0,1]."""
    radii: torch.Tensor
    """[N] int32 3-sigma radius of the major axis in pixels, 0 where culled."""
    bbox: torch.Tensor
    """[N,4] int64 inclusive pixel box (x0, y0, x1, y1) where alpha can reach alpha_min, clipped."""
    visible: torch.Tensor
    """[N] bool: depth within (near, far), opacity >= alpha_min and box inside the image."""


class RenderOutput(NamedTuple):
    """What a backend returns for one camera."""

    image: torch.Tensor
    """[H,W,D] blended features (plus background times the final transmittance)."""
    alpha: torch.Tensor
    """[H,W] accumulated opacity, sum of the blending weights."""
    depth: torch.Tensor
    """[H,W] expected depth sum(w z) / alpha, 0 where alpha is 0."""
    radii: torch.Tensor
    """[N] int32 projected 3-sigma radius in pixels, 0 where culled."""
    means2d: torch.Tensor
    """[N,2] projected centres in pixels (the tensor used for rendering, so its .grad is view-space)."""
    visible: torch.Tensor
    """[N] bool, Gaussians inside the view frustum that can reach alpha_min somewhere on the image."""
    n_contrib: torch.Tensor | None
    """[N] int32 number of pixels where the Gaussian received a non-zero weight (None if unknown)."""
    weight_sum: torch.Tensor | None
    """[N] float64 sum over pixels of the Gaussian's blending weight (None if unknown)."""
