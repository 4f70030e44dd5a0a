"""Which Gaussians carry features: opaque ones that cover more than a couple of pixels in some view."""

from __future__ import annotations

from typing import NamedTuple

import torch

from fmgs.cameras import Camera
from fmgs.field.config import SelectConfig
from fmgs.gaussians import GaussianSet
from fmgs.render.projection import project
from fmgs.render.types import RasterConfig


class Selection(NamedTuple):
    """The kept Gaussians."""

    index: torch.Tensor
    """[M] int64 indices into the scene's Gaussians, increasing."""
    total: int
    """N, the number of Gaussians considered."""

    @property
    def fraction(self) -> float:
        return len(self.index) / max(self.total, 1)


@torch.no_grad()
def select_gaussians(
    gaussians: GaussianSet, cameras: list[Camera], cfg: SelectConfig = SelectConfig()
) -> Selection:
    """Apply the opacity and radius tests over ``cameras`` (the training views, at training resolution)."""
    opac = gaussians.opacities
    keep_opacity = opac > cfg.opacity_min
    big = torch.zeros_like(keep_opacity)
    idx = torch.nonzero(keep_opacity).squeeze(1)
    g = gaussians.subset(idx)
    rc = RasterConfig()
    for cam in cameras:
        proj = project(g.means, g.quats, g.scales, g.opacities, cam, rc)
        big[idx] |= proj.visible & (proj.radii > cfg.radius_min)
    return Selection(torch.nonzero(keep_opacity & big).squeeze(1), len(opac))
