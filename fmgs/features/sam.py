"""SAM as the build's class-agnostic segmenter (``--segmenter facebook/sam-vit-base``, any transformers
``sam`` model or folder): SAM's automatic mask generation, cut down to what segment pooling needs.

A grid of point prompts over the image; for each point SAM proposes three masks with a predicted IoU; a
point's best-scoring mask is kept when SAM trusts it (predicted IoU at least ``pred_iou``) and it is
stable (the IoU of the mask thresholded at +offset and -offset logits, at least ``stability``), as
SAM's own generator filters. The kept masks become one segment map by painting the largest first, so a
small object's mask (or a part's) overwrites the larger one it lies on (``paint_masks``); pixels no kept
mask covers are in no segment and keep their own target. Unlike SAM's generator there are no image crops
and no NMS: painting resolves overlaps, and targets need segments, not a deduplicated mask list.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from fmgs.errors import ValidationError
from fmgs.features.models import DEFAULT_REVISION, ModelFiles, fetch_model, load_guard, require_transformers
from fmgs.features.segment_pool import MIN_PIXELS, relabel

SAM_TYPES = ("sam",)


@dataclass(frozen=True)
class SamMaskConfig:
    """How SAM's masks are asked for and kept (SAM's automatic generator's defaults but for the grid)."""

    points_per_side: int = 16
    """Point prompts per side of the image (SAM's generator: 32; 16 asks 256 prompts, a quarter)."""
    points_per_batch: int = 64
    """Prompts per decoder call (memory)."""
    pred_iou: float = 0.88
    """Smallest predicted IoU a kept mask has."""
    stability: float = 0.95
    """Smallest stability score a kept mask has."""
    stability_offset: float = 1.0
    """Logit offset of the stability score."""
    min_pixels: int = MIN_PIXELS
    """Smaller segments are in no segment."""

    def __post_init__(self) -> None:
        if self.points_per_side < 1 or self.points_per_batch < 1:
            raise ValidationError("points_per_side/points_per_batch", "must be positive")


def stability_score(logits: torch.Tensor, offset: float) -> torch.Tensor:
    """[..., H, W] mask logits -> [...]: |logits > offset| / |logits > -offset| (1 for an empty mask)."""
    inner = (logits > offset).flatten(-2).sum(-1).float()
    outer = (logits > -offset).flatten(-2).sum(-1).float()
    return torch.where(outer > 0, inner / outer.clamp(min=1), torch.ones_like(outer))


def paint_masks(masks: np.ndarray, min_pixels: int = MIN_PIXELS) -> np.ndarray:
    """masks [N,H,W] bool -> [H,W] int64 segment ids 1..n (0: no mask, or a segment under min_pixels):
    the masks painted largest first, so smaller ones overwrite the larger they lie on; ids in order of
    each segment's first pixel (row-major)."""
    if masks.ndim != 3:
        raise ValidationError("masks", f"expected [N,H,W], got {masks.shape}")
    seg = np.zeros(masks.shape[1:], np.int64)  # 0: no mask
    order = np.argsort(-masks.sum((1, 2)), kind="stable")
    for k, i in enumerate(order):
        seg[masks[i]] = k + 1
    return relabel(seg, min_pixels, none=0)


def paint_masks_reference(masks: np.ndarray, min_pixels: int = MIN_PIXELS) -> np.ndarray:
    """``paint_masks`` pixel by pixel: each pixel takes the smallest mask covering it (the later of equal
    sizes), then segments are numbered by first pixel (the exact twin)."""
    n, H, W = masks.shape
    areas = masks.sum((1, 2))
    owner = -np.ones((H, W), np.int64)
    for y in range(H):
        for x in range(W):
            best = None
            for i in range(n):
                if masks[i, y, x] and (best is None or areas[i] <= areas[best]):
                    best = i
            owner[y, x] = -1 if best is None else best
    ids, counts = np.unique(owner[owner >= 0], return_counts=True)
    keep = {int(i) for i, c in zip(ids, counts, strict=True) if c >= min_pixels}
    out = np.zeros((H, W), np.int64)
    nxt = 1
    new: dict[int, int] = {}
    for y in range(H):
        for x in range(W):
            o = int(owner[y, x])
            if o in keep:
                if o not in new:
                    new[o] = nxt
                    nxt += 1
                out[y, x] = new[o]
    return out


class SamSegmenter:
    """A transformers ``SamModel`` and its image processor behind the segmenter interface
    (``segments(image [H,W,3]) -> [H,W] int64``)."""

    def __init__(self, model: Any, processor: Any, model_id: str, device: str | torch.device = "cpu",
                 cfg: SamMaskConfig = SamMaskConfig()) -> None:  # fmt: skip
        self.device = torch.device(device)
        self.model = model.to(self.device).eval()
        self.processor = processor
        self.id = model_id
        self.cfg = cfg
        self.files: ModelFiles | None = None

    @classmethod
    def load(
        cls,
        model_id: str,
        device: str | torch.device = "cpu",
        *,
        revision: str = DEFAULT_REVISION,
        offline: bool | str | None = None,
        cfg: SamMaskConfig = SamMaskConfig(),
    ) -> SamSegmenter:
        """SAM from the folder ``model_id`` (``hf:`` ids too), the hub cache at ``revision`` or a download
        (fmgs.features.models; ``offline`` forbids it)."""
        from fmgs.features.registry import parse_encoder_id, require_type

        ref = parse_encoder_id(model_id)
        if ref.family != "hf":
            raise ValidationError(model_id, "SAM loads transformers models (hf: ids) only")
        files = fetch_model(ref.ref, revision=revision, offline=offline)
        require_type(files.path, model_id, SAM_TYPES, "segmenter")
        transformers = require_transformers()
        with load_guard(files):
            model = transformers.SamModel.from_pretrained(str(files.path), local_files_only=True)
            processor = transformers.SamProcessor.from_pretrained(str(files.path), local_files_only=True)
        seg = cls(model, processor.image_processor, model_id, device, cfg)
        seg.files = files
        return seg

    @torch.inference_mode()
    def masks(self, image: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """image [H,W,3] float RGB in [0,1] -> (kept masks [N,H,W] bool, their predicted IoUs [N])."""
        if image.ndim != 3 or image.shape[-1] != 3:
            raise ValidationError("image", f"expected [H,W,3], got {tuple(image.shape)}")
        H, W = image.shape[:2]
        rgb = (image.detach().float().clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()
        inp = self.processor(images=rgb, return_tensors="pt")
        emb = self.model.get_image_embeddings(inp["pixel_values"].to(self.device))
        rh, rw = (int(v) for v in inp["reshaped_input_sizes"][0])
        n = self.cfg.points_per_side
        ys, xs = (np.arange(n) + 0.5) / n * H, (np.arange(n) + 0.5) / n * W  # cell centres, SAM's grid
        pts = np.stack(np.meshgrid(xs * rw / W, ys * rh / H), -1).reshape(-1, 2)  # (x, y), model frame
        kept, scores = [], []
        for s in range(0, len(pts), self.cfg.points_per_batch):
            p = torch.tensor(pts[s : s + self.cfg.points_per_batch], dtype=torch.float32, device=self.device)
            out = self.model(image_embeddings=emb, input_points=p[None, :, None, :],
                             input_labels=torch.ones(1, len(p), 1, dtype=torch.long, device=self.device),
                             multimask_output=True)  # fmt: skip
            logits = self.processor.post_process_masks(
                out.pred_masks.cpu(), inp["original_sizes"], inp["reshaped_input_sizes"], binarize=False
            )[0]  # [P,3,H,W]
            iou = out.iou_scores[0].cpu()  # [P,3]
            best = iou.argmax(1)
            rows = torch.arange(len(p))
            lg, sc = logits[rows, best], iou[rows, best]
            ok = (sc >= self.cfg.pred_iou) & (
                stability_score(lg, self.cfg.stability_offset) >= self.cfg.stability
            )
            kept.append((lg[ok] > 0).numpy())
            scores.append(sc[ok].numpy())
        masks = np.concatenate(kept) if kept else np.zeros((0, H, W), bool)
        return masks, np.concatenate(scores) if scores else np.zeros(0, np.float32)

    def segments(self, image: torch.Tensor) -> np.ndarray:
        """image [H,W,3] -> [H,W] int64 segment ids (``paint_masks`` of the kept masks)."""
        masks, _ = self.masks(image)
        return paint_masks(masks, self.cfg.min_pixels)
