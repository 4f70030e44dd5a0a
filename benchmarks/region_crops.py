"""Region crops: a CLIP target candidate that embeds one tight crop per segment instead of a lattice of crops.

Mask-based open-vocabulary methods (LangSplat, OpenMask3D, Gaussian Grouping) segment each image (SAM) and
give every pixel of a segment the CLIP embedding of a crop around that segment, so the crop is about the
segment's own object whatever its size. Here the segments come from DINO, as the rest of the build has no
SAM: regions grown over the dense map (``grow_regions``), or, as the upper bound of what better masks
could give, the label masks themselves (``label_regions``). Each region's crop is the square on its
bounding box's longer side, centred on the box and shifted inside the image (``region_boxes``); its
embedding is averaged with the finest scale's map at every pixel of the region (``region_target``), since
the finest crops already speak for the pixel where no region does. With ``masked``, the pixels of the crop
outside the region are black first, as LangSplat feeds CLIP its SAM masks, so a region's crop shows that
region alone (a floor region's crop is otherwise the whole image, named after the objects on it).

Benchmark code (benchmarks/clip_targets.py scores it beside the blends); not a build option.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

import numpy as np
import torch

from fmgs.vecmath import safe_normalize

GROW_COSINE = 0.92
"""A pixel joins a growing region when its unit DINO vector's cosine with the region's mean direction
exceeds this (chosen on dev scenes 301 and 302 among 0.5-0.95: higher splits objects into parts, which
still crop tightly; lower merges objects with the floor, whose crops are then named floor)."""
MIN_PIXELS = 4
"""Smaller regions are left to the finest scale (their crops would be a pixel or two across)."""
BATCH = 64
"""Crops per call of the embedding function."""


def grow_regions(
    dense: torch.Tensor, cosine: float = GROW_COSINE, min_pixels: int = MIN_PIXELS
) -> np.ndarray:
    """dense [h,w,D] DINO map -> [h,w] int64 region ids (1..n; 0: in no region of min_pixels or more).

    Seeds are taken most locally coherent first (the summed cosine with the 3x3 neighbourhood); a region
    grows over 4-neighbours while a neighbour's cosine with the region's mean direction exceeds
    ``cosine``. Comparing with the mean, not with the last pixel, keeps a smooth gradient across a
    boundary from chaining two regions together."""
    d = safe_normalize(dense.float()).cpu().numpy()
    h, w, _ = d.shape
    pad = np.pad(d, ((1, 1), (1, 1), (0, 0)), mode="edge")
    shifts = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
    local = sum((d * pad[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]).sum(-1) for dy, dx in shifts)
    seg = np.zeros((h, w), np.int64)
    n = 0
    for flat in np.argsort(-local.ravel(), kind="stable"):
        y, x = divmod(int(flat), w)
        if seg[y, x]:
            continue
        n += 1
        seg[y, x] = n
        total = d[y, x].astype(np.float64).copy()
        members, todo = [(y, x)], deque([(y, x)])
        while todo:
            cy, cx = todo.popleft()
            mean = total / max(float(np.linalg.norm(total)), 1e-12)  # an all-zero map grows nothing
            for ny, nx in ((cy - 1, cx), (cy + 1, cx), (cy, cx - 1), (cy, cx + 1)):
                if 0 <= ny < h and 0 <= nx < w and not seg[ny, nx] and float(d[ny, nx] @ mean) > cosine:
                    seg[ny, nx] = n
                    total += d[ny, nx]
                    members.append((ny, nx))
                    todo.append((ny, nx))
        if len(members) < min_pixels:
            for my, mx in members:
                seg[my, mx] = -1  # taken, in no region
            n -= 1
    seg[seg < 0] = 0
    return seg


def label_regions(labels: torch.Tensor, min_pixels: int = MIN_PIXELS) -> np.ndarray:
    """[h,w] int labels -> [h,w] int64 region ids: each connected component of one label (ground-truth
    masks: the upper bound of region crops)."""
    from scipy import ndimage

    lab = labels.cpu().numpy()
    seg = np.zeros(lab.shape, np.int64)
    n = 0
    for c in np.unique(lab):
        comp, m = ndimage.label(lab == c)
        for j in range(1, m + 1):
            part = comp == j
            if part.sum() >= min_pixels:
                n += 1
                seg[part] = n
    return seg


def region_boxes(seg: np.ndarray) -> list[tuple[int, tuple[int, int, int, int]]]:
    """[(region id, (x0, y0, x1, y1))]: the square on each region's bounding box's longer side, centred on
    the box and shifted inside the image (x1, y1 exclusive)."""
    from scipy import ndimage

    h, w = seg.shape
    out = []
    for i, box in enumerate(ndimage.find_objects(seg)):  # every region's bounding box in one pass
        if box is None:
            continue
        (y0, y1), (x0, x1) = (box[0].start, box[0].stop), (box[1].start, box[1].stop)
        e = min(h, w, max(y1 - y0, x1 - x0))
        bx = round(min(max((x0 + x1 - e) / 2, 0), w - e))
        by = round(min(max((y0 + y1 - e) / 2, 0), h - e))
        out.append((i + 1, (bx, by, bx + e, by + e)))
    return out


def region_target(
    embed_fn: Callable[[torch.Tensor], torch.Tensor],
    image: torch.Tensor,
    seg: np.ndarray,
    finest: torch.Tensor,
    crop_px: int,
    masked: bool = False,
) -> torch.Tensor:
    """image [H,W,3] (same size as seg), finest [H,W,D] the finest scale's map -> [H,W,D] unit target: at a
    region's pixels the mean of its crop's unit embedding and the unit finest map, elsewhere the finest.
    ``masked``: each crop black outside its region (see the module docstring)."""
    from fmgs.features.pyramid import _cut

    out = safe_normalize(finest.float())
    boxes = region_boxes(seg)
    if not boxes:
        return out
    img = image.permute(2, 0, 1).float()
    ids = torch.from_numpy(seg)
    crops = torch.cat(
        [_cut(img * (ids == r) if masked else img, torch.tensor([b]), crop_px) for r, b in boxes]
    )  # sizes differ: one by one
    emb = torch.cat([embed_fn(crops[i : i + BATCH]) for i in range(0, len(crops), BATCH)])
    emb = safe_normalize(emb.float())
    table = torch.zeros(int(seg.max()) + 1, emb.shape[1])  # region id -> its crop's embedding (0: none)
    table[torch.tensor([r for r, _ in boxes])] = emb
    inside = ids > 0
    out[inside] = safe_normalize(out[inside] + table[ids[inside]])
    return out


def region_cache(data, cache_dir, standin, dino, blend: str = "dominant"):
    """A feature cache of ``data`` whose CLIP targets are region crops over DINO-grown regions
    (``region_target``: each region's crop averaged with the finest scale of the CLIP stand-in's pyramid),
    with the DINO stand-in's maps as the DINO target, for every frame as the build extracts them
    (benchmarks.clip_oracle.write_cache), so that ``fmgs train-field`` distils the candidate as it distils
    the build's own targets. ``blend`` is only the pyramid's setting (the finest scale does not depend on
    it)."""
    from benchmarks.clip_oracle import write_cache
    from fmgs.features.dino import load_dense_encoder
    from fmgs.features.pyramid import pyramid_for, scale_maps
    from fmgs.features.standin import load_standin

    clip = load_standin(f"standin:{standin}")
    cfg = pyramid_for(clip, blend=blend)

    def target(fr, image, hw, dense):
        if tuple(image.shape[:2]) != hw:
            raise ValueError(
                f"{fr.name}: region crops need maps at the image's size {hw}, got {tuple(image.shape[:2])}"
            )
        sm = scale_maps(clip, image, cfg, hw)
        finest = sm.maps[int(torch.tensor(sm.edges).argmin())]
        return region_target(clip, image, grow_regions(dense), finest, clip.image_size)

    return write_cache(data, cache_dir, clip, load_dense_encoder(f"standin-dino:{dino}"), target)
