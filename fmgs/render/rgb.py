"""Render a GaussianSet's colour (SH evaluated per view) through any backend."""

from __future__ import annotations

import torch

from fmgs.cameras import Camera
from fmgs.gaussians import GaussianSet
from fmgs.render import RasterConfig, RenderOutput, rasterize
from fmgs.sh import sh_to_rgb


def render_rgb(
    gaussians: GaussianSet,
    camera: Camera,
    background: torch.Tensor | None = None,
    sh_degree: int | None = None,
    config: RasterConfig | None = None,
    backend: str = "auto",
) -> RenderOutput:
    """RGB image [H,W,3] of ``gaussians`` seen from ``camera`` (view-dependent colour from SH)."""
    g = gaussians
    rgb = sh_to_rgb(g.sh, g.means, camera.center.to(g.means), sh_degree)
    return rasterize(g.means, g.quats, g.scales, g.opacities, rgb, camera, background, config, backend)
