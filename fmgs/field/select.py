"""Which Gaussians carry features.

Rule "coverage" (default): in every pixel of every training view, sort the Gaussians that blend into it
by weight and keep the heaviest until they make up ``coverage`` of the pixel's weight; a Gaussian is
kept if any pixel keeps it. Every pixel's colour is then mostly made of Gaussians with features, so
its rendered feature says what it shows rather than what lies behind a featureless thin object.
Rule "paper": opaque Gaussians that cover more than a couple of pixels in some view (the FMGS code).
With ``max_selected`` K, either rule's choice is cut to the K Gaussians of largest blending weight summed
over every pixel of the training views: the ones that make up most of what the views show.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from fmgs.cameras import Camera
from fmgs.field.config import SelectConfig
from fmgs.gaussians import GaussianSet
from fmgs.render.projection import project
from fmgs.render.types import RasterConfig
from fmgs.render.weights import ViewWeights, view_weights, weights_config


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
    """Apply ``cfg.rule`` over ``cameras`` (the training views; for "coverage" at the resolution the
    features are trained at), then ``cfg.max_selected``."""
    g = gaussians
    weight = None
    if cfg.rule == "coverage":
        keep = torch.zeros(g.num, dtype=torch.bool)
        if cfg.max_selected is not None:
            weight = torch.zeros(g.num, dtype=torch.float64)
        for cam in cameras:
            vw = view_weights(g.means, g.quats, g.scales, g.opacities, cam, weights_config(g.means.device))
            keep[covering(vw, cfg.coverage).cpu()] = True
            if weight is not None:
                weight.index_add_(0, vw.gaussians.cpu(), column_sums(vw).cpu())
    else:
        opac = g.opacities
        keep = (opac > cfg.opacity_min).cpu()
        big = torch.zeros_like(keep)
        idx = torch.nonzero(keep).squeeze(1)
        sub = g.subset(idx)
        rc = RasterConfig()
        for cam in cameras:
            proj = project(sub.means, sub.quats, sub.scales, sub.opacities, cam, rc)
            big[idx] |= (proj.visible & (proj.radii > cfg.radius_min)).cpu()
        keep &= big
    index = torch.nonzero(keep).squeeze(1)
    if cfg.max_selected is not None and len(index) > cfg.max_selected:
        if weight is None:
            weight = summed_weights(g, cameras)
        index = heaviest(index, weight[index], cfg.max_selected)
    return Selection(index, g.num)


def column_sums(vw: ViewWeights) -> torch.Tensor:
    """[M] float64: each of the view's Gaussians' blending weight summed over the view's pixels."""
    csr = vw.matrix.csr
    out = torch.zeros(len(vw.gaussians), dtype=torch.float64, device=csr.values().device)
    return out.index_add_(0, csr.col_indices(), csr.values().double())


def summed_weights(gaussians: GaussianSet, cameras: list[Camera]) -> torch.Tensor:
    """[N] float64: each Gaussian's blending weight summed over every pixel of ``cameras``."""
    g = gaussians
    weight = torch.zeros(g.num, dtype=torch.float64)
    for cam in cameras:
        vw = view_weights(g.means, g.quats, g.scales, g.opacities, cam, weights_config(g.means.device))
        weight.index_add_(0, vw.gaussians.cpu(), column_sums(vw).cpu())
    return weight


def heaviest(index: torch.Tensor, weight: torch.Tensor, k: int) -> torch.Tensor:
    """The ``k`` entries of ``index`` [M] with the largest ``weight`` [M] (ties: the lower index),
    increasing."""
    order = torch.argsort(-weight, stable=True)[:k]
    return torch.sort(index[order]).values


def covering(vw: ViewWeights, coverage: float) -> torch.Tensor:
    """[K] int64 global indices of the Gaussians that, heaviest first, make up the first ``coverage``
    of some pixel's blending weight in view ``vw`` (a Gaussian is kept while the weight before it is
    below coverage x the pixel's total; ties by column order)."""
    csr = vw.matrix.csr
    crow, val = csr.crow_indices(), csr.values().double()
    col = csr.col_indices()
    rows = torch.repeat_interleave(torch.arange(len(crow) - 1, device=val.device), crow[1:] - crow[:-1])
    # Within each row, heaviest first: a stable sort by weight, then a stable sort by row.
    order = torch.argsort(-val, stable=True)
    order = order[torch.argsort(rows[order], stable=True)]
    r, v, c = rows[order], val[order], col[order]
    cum = torch.cumsum(v, 0)
    start = crow[:-1].to(cum.device)
    offset = torch.where(start > 0, cum[(start - 1).clamp_min(0)], torch.zeros_like(cum[: len(start)]))
    before = cum - v - offset[r]  # weight of the heavier Gaussians of the same pixel
    total = torch.zeros(len(crow) - 1, dtype=torch.float64, device=val.device).index_add_(0, rows, val)
    return vw.gaussians[torch.unique(c[before < coverage * total[r]])]


def covering_reference(vw: ViewWeights, coverage: float) -> torch.Tensor:
    """Twin of ``covering``, one pixel at a time from the dense matrix."""
    dense = vw.matrix.csr.to_dense().double()
    kept = set()
    for row in dense:
        nz = [(-float(row[j]), j) for j in range(len(row)) if row[j] != 0]
        total = -sum(w for w, _ in nz)
        acc = 0.0
        for w, j in sorted(nz):
            if acc < coverage * total:
                kept.add(j)
            acc += -w
    return vw.gaussians[torch.tensor(sorted(kept), dtype=torch.int64)]
