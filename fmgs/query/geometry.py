"""Which of a scene's Gaussians a viewer gets as points: those opaque enough, subsampled to a cap."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from fmgs.errors import ValidationError

GEOMETRY_SEED = 0
"""Seed of the subsample: the same request on the same scene gives the same Gaussians."""


class GeometrySelection(NamedTuple):
    index: np.ndarray
    """[k] int64 scene indices, increasing."""
    qualified: int
    """Gaussians with opacity >= min_opacity (k <= qualified)."""


def select_geometry(
    opacity_logits: torch.Tensor, max_gaussians: int, min_opacity: float
) -> GeometrySelection:
    """The Gaussians (opacity logits [N]) whose opacity is at least ``min_opacity``; when more than
    ``max_gaussians`` qualify, a uniform random sample of that many (seed GEOMETRY_SEED), so the points'
    density follows the scene's. Indices come back sorted."""
    if max_gaussians < 1:
        raise ValidationError("max_gaussians", f"must be >= 1, got {max_gaussians}")
    if not 0.0 <= min_opacity < 1.0:
        raise ValidationError("min_opacity", f"must lie in [0, 1), got {min_opacity}")
    logits = opacity_logits.detach().cpu()
    if min_opacity > 0.0:
        # The opacity exactly as the Gaussians' columns report it (float64 sigmoid rounded to float32).
        opacity = torch.sigmoid(logits.double()).float()
        idx = torch.nonzero(opacity >= min_opacity).flatten().numpy()
    else:
        idx = np.arange(len(logits), dtype=np.int64)
    qualified = len(idx)
    if qualified > max_gaussians:
        pick = np.random.default_rng(GEOMETRY_SEED).choice(qualified, size=max_gaussians, replace=False)
        idx = idx[np.sort(pick)]
    return GeometrySelection(idx.astype(np.int64, copy=False), qualified)
