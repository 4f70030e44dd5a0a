"""Mask pooling: one embedding per segment of a class-agnostic segmentation (SAM's masks, or the segmenter
stand-in's, fmgs.features.standin_seg).

The finest crops of the pyramid are the most local, but each alone names its pixel wrongly often (a crop
of a stripe of a striped mug is not a mug); averaged over every pixel of the mug's mask, the crops that
saw the mug outvote the few that did not, and the mask's boundary stops the floor's crops from mixing
in. This is how mask-based open-vocabulary methods classify a segment (mask-pooled CLIP features:
OVSeg, FC-CLIP, OpenMask3D's per-mask feature), applied to the target maps before distillation.

Pure torch; works on any device.
"""

from __future__ import annotations

import numpy as np
import torch

from fmgs.errors import ValidationError
from fmgs.vecmath import safe_normalize

MIN_PIXELS = 4
"""Segmenters return smaller segments as 0 (in no segment): too small to crop or pool."""


def pool_segments(target: torch.Tensor, segments: torch.Tensor) -> torch.Tensor:
    """target [h,w,D] (unit or not), segments [h,w] int64 ids (0: in no segment) -> [h,w,D] unit: at each
    pixel of segment k the normalised mean of the unit target vectors over k; pixels of id 0 keep their
    own (normalised)."""
    if segments.shape != target.shape[:2]:
        raise ValidationError(
            "segments",
            f"must be the target map's size {tuple(target.shape[:2])}, got {tuple(segments.shape)}",
        )
    if segments.numel() and int(segments.min()) < 0:
        raise ValidationError("segments", "ids must be >= 0")
    unit = safe_normalize(target.float())
    ids = segments.to(unit.device).reshape(-1).long()
    D = unit.shape[-1]
    n = int(ids.max()) + 1 if ids.numel() else 1
    sums = torch.zeros(n, D, device=unit.device).index_add_(0, ids, unit.reshape(-1, D))
    pooled = safe_normalize(sums)[ids].reshape(unit.shape)
    return torch.where((ids > 0).reshape(*unit.shape[:2], 1), pooled, unit)


def pool_segments_reference(target: torch.Tensor, segments: torch.Tensor) -> torch.Tensor:
    """``pool_segments`` one segment at a time (the reference twin)."""
    unit = safe_normalize(target.float())
    out = unit.clone()
    for k in segments.unique().tolist():
        if k > 0:
            m = segments == k
            out[m] = safe_normalize(unit[m].sum(0, keepdim=True))
    return out


def resize_segments(segments: torch.Tensor, hw: tuple[int, int]) -> torch.Tensor:
    """segments [H,W] -> [h,w] by nearest neighbour (ids are not to be interpolated)."""
    if tuple(segments.shape) == tuple(hw):
        return segments
    x = segments[None, None].float()
    return torch.nn.functional.interpolate(x, size=tuple(hw), mode="nearest")[0, 0].long()


def relabel(comp: np.ndarray, min_pixels: int, none: int | None = None) -> np.ndarray:
    """Component ids [H,W] -> ids 1..n in order of first pixel, components under min_pixels (and the id
    ``none``, when given: pixels in no component) as 0."""
    values, first, inverse, counts = np.unique(comp.ravel(), return_index=True, return_inverse=True,
                                               return_counts=True)  # fmt: skip
    keep = (counts >= min_pixels) & (values != none if none is not None else True)
    order = np.argsort(first, kind="stable")  # components in order of their first pixel
    new = np.zeros(len(first), np.int64)
    kept = order[keep[order]]
    new[kept] = np.arange(1, len(kept) + 1)
    return new[inverse].reshape(comp.shape)
