"""Blending the crop pyramid's per-scale maps into one target map, per pixel.

A crop's CLIP embedding describes what the crop shows: the pixel's own object when the crop is mostly that
object, its surroundings when the object is a small part of it. The paper's hybrid target averages the
seven scales with equal weight, so on an object a tenth of the image the coarse crops (a quarter to half of
it) speak mostly for the neighbours and outvote the fine ones. The blends here weigh each scale at each
pixel by how much of that scale's crop is the pixel's own region, judged by the dense DINO features: a
crop whose DINO features are like the pixel's is about the pixel's region.

- ``mean``: the paper's equal mean (no DINO needed).
- ``coherence``: weight of scale s at pixel p = max(0, c_s(p)), where c_s(p) = d_p . mean_{q in box_s(p)} d_q
  is the mean DINO cosine between p and the pixels of a box of scale s's crop edge about p (unit DINO
  vectors; boxes shifted inside the image as crops are); for a region of DINO vectors alike and unlike
  the rest, c_s is the region's share of the box.
- ``dominant``: the scales whose box is at least half the pixel's region (c_s >= c_finest / 2), equally:
  the crops CLIP would name for the pixel's own object; the finest scale always counts.

``pool_regions`` then optionally averages a map within DINO-coherent neighbourhoods (a joint bilateral
filter guided by DINO), the soft counterpart of pooling features inside a segment mask.

Pure torch; every function works on any device. The per-scale maps come from fmgs.features.pyramid.
"""

from __future__ import annotations

import torch

from fmgs.errors import ValidationError
from fmgs.features.sizes import SCALE_BLENDS as BLENDS
from fmgs.vecmath import safe_normalize


def box_mean(x: torch.Tensor, r: int) -> torch.Tensor:
    """x [h,w,D] -> [h,w,D]: the mean over the (2r+1) x (2r+1) box about each pixel, the box shifted to
    lie inside the image (clipped to it when larger), as the pyramid clamps its crops inside."""
    if r < 0:
        raise ValidationError("r", f"must be >= 0, got {r}")
    out = x
    for axis in (0, 1):
        L = out.shape[axis]
        k = min(2 * r + 1, L)
        cs = torch.cat([torch.zeros_like(out.narrow(axis, 0, 1)), out.cumsum(axis)], axis)
        start = (torch.arange(L, device=x.device) - r).clamp(0, L - k)
        out = (cs.index_select(axis, start + k) - cs.index_select(axis, start)) / k
    return out


def box_mean_reference(x: torch.Tensor, r: int) -> torch.Tensor:
    """``box_mean`` by explicit loops (the reference twin)."""
    h, w = x.shape[:2]
    out = torch.empty_like(x)
    ky, kx = min(2 * r + 1, h), min(2 * r + 1, w)
    for i in range(h):
        y0 = min(max(i - r, 0), h - ky)
        for j in range(w):
            x0 = min(max(j - r, 0), w - kx)
            out[i, j] = x[y0 : y0 + ky, x0 : x0 + kx].reshape(-1, x.shape[-1]).mean(0)
    return out


def coherence(dense: torch.Tensor, edges: list[float]) -> torch.Tensor:
    """[S,h,w] c_s(p): the mean cosine between p's dense feature and those of the box of edge ``edges[s]``
    map pixels about p (see the module docstring). dense [h,w,Dd], not necessarily unit."""
    d = safe_normalize(dense.float())
    out = []
    for e in edges:
        r = max(0, round((float(e) - 1.0) / 2.0))
        out.append((d * box_mean(d, r)).sum(-1))
    return torch.stack(out)


def scale_weights(blend: str, dense: torch.Tensor | None, edges: list[float]) -> torch.Tensor | None:
    """[S,h,w] non-negative weights of each scale at each pixel (scales ordered as ``edges``, finest
    first), or None for the equal mean. ``edges``: each scale's crop edge in map pixels."""
    if blend not in BLENDS:
        raise ValidationError("scale blend", f"must be one of {BLENDS}, got {blend!r}")
    if blend == "mean":
        return None
    if dense is None:
        raise ValidationError(
            "scale blend", f"{blend!r} weighs scales by DINO coherence and needs the dense (DINO) map"
        )
    c = coherence(dense, edges)
    finest = int(torch.tensor(edges).argmin())
    if blend == "coherence":
        w = c.clamp(min=0.0)
    else:  # dominant
        w = (c >= 0.5 * c[finest]).float()
    w[finest] = w[finest].clamp(min=1e-6)  # the finest crop always speaks for the pixel
    return w


def blend_scales(maps: list[torch.Tensor], weights: torch.Tensor | None) -> torch.Tensor:
    """maps: S of [h,w,D] per-scale maps; weights [S,h,w] or None (equal) -> [h,w,D] unit-norm target."""
    if weights is None:
        return safe_normalize(sum(maps) / len(maps))
    if weights.shape[0] != len(maps):
        raise ValidationError("weights", f"{weights.shape[0]} scales of weights for {len(maps)} maps")
    acc = sum(w[..., None] * m for w, m in zip(weights, maps, strict=True))
    return safe_normalize(acc / weights.sum(0)[..., None])


def pool_regions(target: torch.Tensor, dense: torch.Tensor, radius: int) -> torch.Tensor:
    """target [h,w,D] averaged, at each pixel p, over the pixels q within ``radius`` (a square) weighted by
    max(0, d_p . d_q)^2 (unit DINO vectors, dense [h,w,Dd]): pixels DINO groups with p count, others
    barely. Returns [h,w,D] unit-norm."""
    h, w = target.shape[:2]
    d = safe_normalize(dense.float())
    acc = torch.zeros_like(target, dtype=torch.float32)
    norm = torch.zeros(h, w, device=target.device)
    for dy in range(-radius, radius + 1):
        ys, yt = slice(max(0, -dy), h - max(0, dy)), slice(max(0, dy), h - max(0, -dy))
        for dx in range(-radius, radius + 1):
            xs, xt = slice(max(0, -dx), w - max(0, dx)), slice(max(0, dx), w - max(0, -dx))
            a = (d[ys, xs] * d[yt, xt]).sum(-1).clamp(min=0.0) ** 2
            acc[ys, xs] += a[..., None] * target[yt, xt].float()
            norm[ys, xs] += a
    return safe_normalize(acc / norm.clamp(min=1e-12)[..., None])
