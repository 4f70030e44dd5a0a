"""Render a GaussianSet's colour (SH evaluated per view) through any backend."""

from __future__ import annotations

from collections.abc import Callable

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
    between_tiles: Callable[[], None] | None = None,
) -> RenderOutput:
    """RGB image [H,W,3] of ``gaussians`` seen from ``camera`` (view-dependent colour from SH);
    ``between_tiles`` as in ``rasterize``."""
    g = gaussians
    rgb = sh_to_rgb(g.sh, g.means, camera.center.to(g.means), sh_degree)
    return rasterize(
        g.means, g.quats, g.scales, g.opacities, rgb, camera, background, config, backend, between_tiles
    )
