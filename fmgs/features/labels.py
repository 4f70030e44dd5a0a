"""Language targets from label masks: each pixel gets the text embedding of its label's name.

For scenes with per-pixel labels (e.g. ``fmgs.synth``) this replaces the CLIP pyramid with an exact,
cheap target in any text encoder's space. Downsampling averages embeddings over the exact area each
output pixel covers (ignored labels excluded), then renormalises; an output pixel is supervised when
more than half of its area is not ignored.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from fmgs.errors import ValidationError
from fmgs.features.text import TextEncoder
from fmgs.vecmath import safe_normalize


class LabelTargets(NamedTuple):
    """Dense language target from a label map."""

    clip: torch.Tensor
    """[h,w,D] float32, unit-norm where any non-ignored label covers the pixel, else zero."""
    mask: torch.Tensor
    """[h,w] bool: True where the majority of the pixel's area has a non-ignored label."""


def area_matrix(src_len: int, out_len: int) -> torch.Tensor:
    """[out_len, src_len] float64: share of output pixel o's span covered by source pixel i (rows sum to 1).

    Output pixel o spans [o*r, (o+1)*r) source pixels with r = src_len / out_len (any ratio, up or down).
    """
    r = src_len / out_len
    lo = torch.arange(out_len, dtype=torch.float64)[:, None] * r
    i = torch.arange(src_len, dtype=torch.float64)[None, :]
    overlap = (torch.minimum(i + 1, lo + r) - torch.maximum(i, lo)).clamp_min(0.0)
    return overlap / r


def label_embedding_map(
    labels: torch.Tensor,
    embeddings: torch.Tensor,
    out_hw: tuple[int, int],
    ignore: frozenset[int] | set[int] = frozenset({0}),
) -> LabelTargets:
    """labels [H,W] integer in [0, L) or in ``ignore`` (an ignored id needs no row: 255 "void" with fewer
    names), embeddings [L,D] (row l for label l) -> targets at out_hw = (h, w)."""
    if labels.ndim != 2 or labels.dtype.is_floating_point or labels.dtype == torch.bool:
        raise ValidationError(
            "labels", f"expected an integer [H,W] map, got {labels.dtype} {tuple(labels.shape)}"
        )
    if embeddings.ndim != 2 or not torch.isfinite(embeddings).all():
        raise ValidationError("embeddings", f"expected finite [L,D], got {tuple(embeddings.shape)}")
    L = embeddings.shape[0]
    present = torch.unique(labels).tolist()
    bad = [v for v in present if not 0 <= v < L and v not in ignore]
    if bad:
        raise ValidationError("labels", f"label value {bad[0]} outside [0, {L}) (all bad values: {bad[:10]})")
    h, w = int(out_hw[0]), int(out_hw[1])
    if h < 1 or w < 1:
        raise ValidationError("out_hw", f"must be positive, got {out_hw}")
    H, W = labels.shape
    ay = area_matrix(H, h).to(labels.device)  # [h, H]
    ax = area_matrix(W, w).to(labels.device)  # [w, W]
    emb = embeddings.to(labels.device, torch.float64)
    acc = torch.zeros(h, w, emb.shape[1], dtype=torch.float64, device=labels.device)
    valid = torch.zeros(h, w, dtype=torch.float64, device=labels.device)
    for v in present:
        if v in ignore:
            continue
        frac = ay @ (labels == v).to(torch.float64) @ ax.T  # [h, w] area fraction of label v
        acc += frac[..., None] * emb[v]
        valid += frac
    clip = safe_normalize(acc).float()
    return LabelTargets(clip, valid > 0.5 + 1e-9)


def label_map_targets(
    labels: torch.Tensor,
    names: list[str],
    encoder: TextEncoder,
    out_hw: tuple[int, int],
    ignore: frozenset[int] | set[int] = frozenset({0}),
) -> LabelTargets:
    """labels [H,W] indexing ``names`` -> targets in ``encoder``'s space at out_hw; names embedded once."""
    emb = encoder.encode_text(list(names)).to(labels.device, torch.float32)
    return label_embedding_map(labels, emb, out_hw, ignore)
