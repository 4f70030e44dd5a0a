"""Hybrid CLIP targets: embeddings of overlapping square crops at several scales, blended into a dense map.

Geometry (pure, testable):

- A crop at scale ``s`` is a square of ``c = round(s * min(H, W))`` pixels (at least 1).
- Along an axis of length ``L`` the crops start at ``n`` evenly spaced positions from 0 to ``L - c``
  (rounded to whole pixels), with ``n`` the smallest count whose spacing is at most the nominal stride
  ``c * (1 - overlap)``, capped at ``max_stride * min(H, W)`` when a cap is set. So crops cover the
  image, never leave it, and overlap at least as requested; the first and last crop touch the image
  border (the "edge crops clamped inside").
- Each crop's embedding is placed at the crop centre (continuous pixel coordinates: pixel ``j`` spans
  ``[j, j+1)``, its centre is ``j + 0.5``). A scale's [ny, nx, D] grid is interpolated to the output
  pixels' centres bilinearly through the actual crop centres (piecewise linear per axis, clamped to the
  outermost centres, i.e. ``align_corners=True`` on the crop-centre lattice, border padding outside it).
- The per-scale maps are blended per pixel (fmgs.features.scale_blend: the paper's equal mean, or weights
  from the DINO map's coherence over each scale's crop) and each pixel renormalised to unit length.

Scales default to 7 values spaced linearly from 0.05 to 0.5 of min(H, W) (the LERF/FMGS pyramid).

The stride cap (``max_stride``, default 0.05 of min(H, W): the finest crop's edge) is ours, not the
paper's. With strides of half the crop edge alone, a coarse scale's map at a pixel interpolates crops
centred up to a quarter of the image away, so on objects smaller than that spacing the coarse scales,
averaged with equal weight, outvote the fine ones, although each crop is right about its own centre.
Sampling every scale at least as densely as the finest crop resolves keeps the coarse context and puts
it where it belongs, for more crops; benchmarks/results/CLIP_PATH.md measures both sides of this knob.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F

from fmgs.errors import ValidationError
from fmgs.features.scale_blend import BLENDS, blend_scales, scale_weights
from fmgs.features.sizes import CROP_SCALES, CROP_STRIDE


@dataclass(frozen=True)
class PyramidConfig:
    """Crop pyramid of the hybrid CLIP target."""

    scales: tuple[float, ...] = CROP_SCALES
    """Crop edge as a fraction of min(H, W), one entry per scale (each in (0, 1])."""
    overlap: float = 0.5
    """Minimum overlap of neighbouring crops as a fraction of the crop edge (nominal stride c*(1-overlap))."""
    max_stride: float | None = CROP_STRIDE
    """Crops of every scale start at most this fraction of min(H, W) apart (at least 1 pixel); None: the
    nominal stride alone (the paper's lattice, sparse at the coarse scales)."""
    crop_px: int = 224
    """Edge in pixels each crop is resized to before embedding (the model's input size)."""
    batch_size: int = 64
    """Crops per call of the embedding function."""
    blend: str = "mean"
    """How the scales' maps become one (fmgs.features.scale_blend.BLENDS): "mean" (the paper's equal
    mean), "coherence" or "dominant" (weights from the dense DINO map, which ``hybrid_map`` then needs)."""

    def __post_init__(self) -> None:
        if not self.scales or not all(0.0 < s <= 1.0 for s in self.scales):
            raise ValidationError("scales", f"need at least one scale in (0, 1], got {self.scales}")
        if not 0.0 <= self.overlap < 1.0:
            raise ValidationError("overlap", f"must lie in [0, 1), got {self.overlap}")
        if self.max_stride is not None and not 0.0 < self.max_stride <= 1.0:
            raise ValidationError("max_stride", f"must lie in (0, 1] or be None, got {self.max_stride}")
        if self.crop_px < 1 or self.batch_size < 1:
            raise ValidationError("crop_px/batch_size", "must be positive")

        if self.blend not in BLENDS:
            raise ValidationError("blend", f"must be one of {BLENDS}, got {self.blend!r}")


def pyramid_for(
    encoder,
    single_scale: bool = False,
    max_stride: float | None = PyramidConfig.max_stride,
    blend: str = PyramidConfig.blend,
    finest_only: bool = False,
    scales: tuple[float, ...] = PyramidConfig.scales,
) -> PyramidConfig:
    """The build's pyramid for an image encoder: crops resized once, to the encoder's own input size (224
    for the default ViT-B/16); ``single_scale``: the ablation's one scale (0.25) instead of ``scales``;
    ``max_stride``: the crop lattice's stride cap (PyramidConfig.max_stride); ``blend``:
    PyramidConfig.blend; ``finest_only``: the finest of ``scales`` alone, what segment pooling takes
    (fmgs.features.segment_pool)."""
    if single_scale and finest_only:
        raise ValidationError("pyramid", "single_scale (0.25) and finest_only exclude each other")
    size = int(getattr(encoder, "image_size", PyramidConfig.crop_px))
    if single_scale:
        scales = (0.25,)
    if finest_only:
        scales, blend = (min(scales),), "mean"
    return PyramidConfig(scales=scales, crop_px=size, max_stride=max_stride, blend=blend)


def spec_pyramid(encoder, spec) -> PyramidConfig:
    """``pyramid_for`` with a build's target settings (a fmgs.build.config.TargetSpec: its scales, stride
    cap, blend and what a segmenter pools), the one place the build and its Ray workers map them."""
    return pyramid_for(
        encoder, spec.single_scale, spec.crop_stride, spec.scale_blend, spec.pools_finest, spec.crop_scales
    )


class CropGrid(NamedTuple):
    """Square crops of one scale laid out as a grid."""

    boxes: torch.Tensor
    """[ny, nx, 4] int64 boxes (x0, y0, x1, y1) in pixels, x1/y1 exclusive."""
    centers_x: torch.Tensor
    """[nx] float64 crop centres along x, continuous pixel coordinates."""
    centers_y: torch.Tensor
    """[ny] float64 crop centres along y."""
    size: int
    """Crop edge c in pixels."""


def _axis_starts(L: int, c: int, stride: float) -> torch.Tensor:
    """[n] int64 crop starts along an axis of length L: evenly spread from 0 to L - c, spacing <= stride."""
    if L <= c:
        return torch.zeros(1, dtype=torch.int64)
    n = math.ceil((L - c) / stride - 1e-9) + 1
    pos = torch.linspace(0.0, float(L - c), n, dtype=torch.float64)
    return torch.floor(pos + 0.5).to(torch.int64)  # round half up: spacing >= 1 keeps starts distinct


def crop_grid(H: int, W: int, scale: float, overlap: float, max_stride: float | None = None) -> CropGrid:
    """The crops of one scale for an H x W image (see the module docstring for the layout); ``max_stride``:
    the stride cap as a fraction of min(H, W), None for none."""
    if H < 1 or W < 1:
        raise ValidationError("image", f"size must be positive, got {W}x{H}")
    if not 0.0 < scale <= 1.0 or not 0.0 <= overlap < 1.0:
        raise ValidationError(
            "scale/overlap", f"need scale in (0,1], overlap in [0,1); got {scale}, {overlap}"
        )
    c = max(1, round(scale * min(H, W)))
    stride = c * (1.0 - overlap)
    if max_stride is not None:
        stride = min(stride, max_stride * min(H, W))
    stride = max(1.0, stride)
    xs, ys = _axis_starts(W, c, stride), _axis_starts(H, c, stride)
    y0, x0 = torch.meshgrid(ys, xs, indexing="ij")
    boxes = torch.stack([x0, y0, x0 + c, y0 + c], -1)
    return CropGrid(boxes, xs.double() + c / 2, ys.double() + c / 2, c)


def interp_matrix(centers: torch.Tensor, out_len: int, src_len: int) -> torch.Tensor:
    """[out_len, n] float64 weights of linear interpolation from samples at ``centers`` (pixels of a
    src_len axis) to the centres of out_len output pixels spanning the same axis; clamped at both ends.
    Rows sum to 1.
    """
    n = centers.numel()
    if n == 1:
        return torch.ones(out_len, 1, dtype=torch.float64)
    x = (torch.arange(out_len, dtype=torch.float64) + 0.5) * (src_len / out_len)
    c = centers.to(torch.float64)
    i = (torch.searchsorted(c, x, right=True) - 1).clamp(0, n - 2)
    t = ((x - c[i]) / (c[i + 1] - c[i])).clamp(0.0, 1.0)
    m = torch.zeros(out_len, n, dtype=torch.float64)
    rows = torch.arange(out_len)
    m[rows, i] = 1.0 - t
    m[rows, i + 1] += t
    return m


def _cut(img: torch.Tensor, boxes: torch.Tensor, crop_px: int) -> torch.Tensor:
    """img [3,H,W], boxes [B,4] of one size c -> [B,3,crop_px,crop_px]."""
    crops = torch.stack([img[:, y0:y1, x0:x1] for x0, y0, x1, y1 in boxes.tolist()])
    if crops.shape[-1] != crop_px:
        crops = F.interpolate(
            crops, size=(crop_px, crop_px), mode="bilinear", align_corners=False, antialias=True
        )
    return crops


def scale_grid_embeddings(
    embed_fn: Callable[[torch.Tensor], torch.Tensor],
    img: torch.Tensor,
    grid: CropGrid,
    cfg: PyramidConfig,
    bar=None,
) -> torch.Tensor:
    """img [3,H,W] -> [ny, nx, D] float32 embeddings of the grid's crops, on img's device."""
    flat = grid.boxes.reshape(-1, 4)
    out = []
    for s in range(0, len(flat), cfg.batch_size):
        batch = flat[s : s + cfg.batch_size]
        emb = embed_fn(_cut(img, batch, cfg.crop_px))
        if emb.ndim != 2 or emb.shape[0] != len(batch):
            raise ValidationError(
                "embed_fn", f"returned {tuple(emb.shape)} for {len(batch)} crops, expected [B,D]"
            )
        out.append(emb.to(img.device, torch.float32))
        if bar is not None:
            bar.update(len(batch))
    ny, nx = grid.boxes.shape[:2]
    return torch.cat(out).reshape(ny, nx, -1)


def scale_map(
    embed_fn: Callable[[torch.Tensor], torch.Tensor],
    img: torch.Tensor,
    grid: CropGrid,
    cfg: PyramidConfig,
    out_hw: tuple[int, int],
    bar=None,
) -> torch.Tensor:
    """One scale's map: img [3,H,W] -> [h,w,D] float32 (out_hw = (h, w)), the grid's crop embeddings
    interpolated bilinearly through the crop centres to the output pixels' centres (not normalised)."""
    H, W = img.shape[1:]
    return grid_map(scale_grid_embeddings(embed_fn, img, grid, cfg, bar), grid, (H, W), out_hw)


def grid_map(
    emb: torch.Tensor, grid: CropGrid, image_hw: tuple[int, int], out_hw: tuple[int, int]
) -> torch.Tensor:
    """The grid's crop embeddings emb [ny,nx,D] of an image of ``image_hw`` interpolated bilinearly
    through the crop centres to the output pixels' centres: [h,w,D] float32 (out_hw = (h, w))."""
    (H, W), (h, w) = image_hw, out_hw
    ay = interp_matrix(grid.centers_y, h, H).to(emb.device, torch.float32)  # [h, ny]
    ax = interp_matrix(grid.centers_x, w, W).to(emb.device, torch.float32)  # [w, nx]
    return torch.einsum("hy,ywd->hwd", ay, torch.einsum("yxd,wx->ywd", emb.float(), ax))


def _check_image(image: torch.Tensor, out_hw: tuple[int, int]) -> tuple[int, int]:
    if image.ndim != 3 or image.shape[-1] != 3:
        raise ValidationError("image", f"expected [H,W,3], got {tuple(image.shape)}")
    if not torch.isfinite(image).all():
        raise ValidationError("image", "contains NaN or Inf")
    h, w = int(out_hw[0]), int(out_hw[1])
    if h < 1 or w < 1:
        raise ValidationError("out_hw", f"must be positive, got {out_hw}")
    return h, w


class ScaleMaps(NamedTuple):
    """Every scale's map of one image."""

    maps: list[torch.Tensor]
    """One [h,w,D] float32 map per scale (cfg.scales order), not normalised."""
    edges: list[float]
    """Each scale's crop edge in map pixels (the crop's pixels times h / H)."""
    crops: int
    """Crops embedded."""


def scale_maps(
    embed_fn: Callable[[torch.Tensor], torch.Tensor],
    image: torch.Tensor,
    cfg: PyramidConfig,
    out_hw: tuple[int, int],
    progress: bool = False,
) -> ScaleMaps:
    """image [H,W,3] float RGB in [0,1] -> every scale's map at out_hw (``ScaleMaps``); ``embed_fn`` maps
    crops [B,3,S,S] (S = cfg.crop_px, RGB in [0,1]) to embeddings [B,D]."""
    h, w = _check_image(image, out_hw)
    H, W = image.shape[:2]
    img = image.permute(2, 0, 1).float()
    grids = [crop_grid(H, W, s, cfg.overlap, cfg.max_stride) for s in cfg.scales]
    from tqdm.auto import tqdm

    total = sum(g.boxes.shape[0] * g.boxes.shape[1] for g in grids)
    maps = []
    with tqdm(total=total, desc="clip crops", unit="crop", disable=not progress, leave=False) as bar:
        for g in grids:
            maps.append(scale_map(embed_fn, img, g, cfg, (h, w), bar))
    return ScaleMaps(maps, [g.size * h / H for g in grids], total)


def hybrid_map(
    embed_fn: Callable[[torch.Tensor], torch.Tensor],
    image: torch.Tensor,
    cfg: PyramidConfig,
    out_hw: tuple[int, int],
    progress: bool = False,
    dense: torch.Tensor | None = None,
) -> torch.Tensor:
    """The hybrid multi-scale embedding map of one image.

    image [H,W,3] float RGB in [0,1]; ``embed_fn`` maps crops [B,3,S,S] (S = cfg.crop_px, RGB in [0,1])
    to embeddings [B,D]; ``dense`` [h,w,Dd]: the image's DINO map at out_hw, which the DINO-weighted
    blends need (cfg.blend). Returns [h,w,D] float32 (out_hw = (h, w)) on image's device, unit-norm per
    pixel.
    """

    h, w = _check_image(image, out_hw)
    if dense is not None and tuple(dense.shape[:2]) != (h, w):
        raise ValidationError("dense", f"map is {tuple(dense.shape[:2])}, the target is {(h, w)}")
    weights_needed = cfg.blend != "mean"
    if weights_needed and dense is None:  # before any crop is embedded
        scale_weights(cfg.blend, None, [])
    sm = scale_maps(embed_fn, image, cfg, (h, w), progress)
    weights = scale_weights(cfg.blend, dense.to(image.device) if weights_needed else None, sm.edges)
    return blend_scales(sm.maps, weights)
