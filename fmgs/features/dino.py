"""Dense DINO features: one pass of a ViT (DINO v1 ViT-S/8 by default), patch tokens as a feature map."""

from __future__ import annotations

import os
from typing import Any

import torch
import torch.nn.functional as F

from fmgs.errors import ValidationError
from fmgs.features.models import (
    DEFAULT_DINO_ID,
    DEFAULT_REVISION,
    ModelFiles,
    fetch_model,
    load_guard,
    require_transformers,
)
from fmgs.features.registry import DENSE_TYPES, parse_encoder_id, require_type
from fmgs.features.standin_dino import load_standin_dino

IMAGENET_MEAN = (0.485, 0.456, 0.406)
"""Per-channel RGB mean DINO was trained with (ImageNet)."""
IMAGENET_STD = (0.229, 0.224, 0.225)
"""Per-channel RGB standard deviation DINO was trained with (ImageNet)."""
DEFAULT_SHORT_SIDE = 448
"""Default input short side in pixels: 56 patches of 8 px, ~4K tokens for a 4:3 image (one ViT-S pass)."""


class DinoEncoder:
    """Dense patch features of a DINO ``transformers.ViTModel`` or a DINOv2 ``Dinov2Model`` (with or
    without registers): the CLS token and any register tokens dropped, not normalised.

    The image is resized so its short side is ``short_side`` and both sides are multiples of the patch
    size (aspect kept up to one patch), run once with interpolated position embeddings, and the
    [h/p, w/p, D] token grid is resized bilinearly to the requested size. Each token stands for its
    patch, so the grid tiles the image: ``align_corners=False`` maps patch centres to pixel positions.
    """

    def __init__(
        self,
        model: Any,
        model_id: str,
        device: str | torch.device = "cpu",
        short_side: int = DEFAULT_SHORT_SIDE,
        mean: tuple[float, float, float] = IMAGENET_MEAN,
        std: tuple[float, float, float] = IMAGENET_STD,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        """Wrap an existing ``ViTModel`` (moved to ``device``/``dtype`` and set to eval, in place).

        ``dtype`` (e.g. float16 on a GPU) is the model's compute type; outputs are float32.
        """
        self.device = torch.device(device)
        self.dtype = dtype
        self.model = model.to(self.device, dtype).eval()
        self.id = model_id
        self.files: ModelFiles | None = None
        """Where the weights came from, when loaded by id."""
        self.dim = int(model.config.hidden_size)
        self.patch = int(model.config.patch_size)
        self.skip = 1 + int(getattr(model.config, "num_register_tokens", 0) or 0)
        """Tokens before the patch grid: CLS, then DINOv2's register tokens."""
        # ViT interpolates its position embeddings only when asked; DINOv2 always does.
        self.forward_kwargs = {"interpolate_pos_encoding": True} if model.config.model_type == "vit" else {}
        if short_side < self.patch:
            raise ValidationError("short_side", f"{short_side} is smaller than the patch size {self.patch}")
        self.short_side = short_side
        self.mean = torch.tensor(mean, dtype=torch.float32, device=self.device).view(1, 3, 1, 1)
        self.std = torch.tensor(std, dtype=torch.float32, device=self.device).view(1, 3, 1, 1)

    @classmethod
    def load(
        cls,
        model_id: str = DEFAULT_DINO_ID,
        model_dir: str | os.PathLike | None = None,
        device: str | torch.device = "cpu",
        short_side: int = DEFAULT_SHORT_SIDE,
        dtype: torch.dtype = torch.float32,
        *,
        revision: str = DEFAULT_REVISION,
        offline: bool | str | None = None,
    ) -> DinoEncoder:
        """Load DINO (``vit``) or DINOv2 (``dinov2``, ``dinov2_with_registers``) from ``model_dir``, the
        folder ``model_id`` (``hf:`` ids too), the hub cache at ``revision`` or a download
        (fmgs.features.registry; ``offline`` forbids it)."""

        ref = parse_encoder_id(model_id)
        if ref.family != "hf":
            raise ValidationError(model_id, "the dense regulariser loads transformers models (hf: ids) only")
        files = fetch_model(ref.ref, model_dir, revision=revision, offline=offline)
        kind = require_type(files.path, model_id, DENSE_TYPES, "dense regulariser")
        transformers = require_transformers()
        d = str(files.path)
        with load_guard(files):
            if kind == "vit":
                kw = {"add_pooling_layer": False, "local_files_only": True}
                model = transformers.ViTModel.from_pretrained(d, **kw)
            elif kind == "dinov2":
                model = transformers.Dinov2Model.from_pretrained(d, local_files_only=True)
            else:
                model = transformers.Dinov2WithRegistersModel.from_pretrained(d, local_files_only=True)
        enc = cls(model, model_id, device, short_side, dtype=dtype)
        enc.files = files
        return enc

    def input_size(self, H: int, W: int) -> tuple[int, int]:
        """(h, w) the network sees for an H x W image: multiples of the patch, short side ``short_side``."""
        p = self.patch
        short = max(p, round(self.short_side / p) * p)
        f = short / min(H, W)
        h = short if H <= W else max(p, round(H * f / p) * p)
        w = short if W < H else max(p, round(W * f / p) * p)
        return h, w

    @torch.inference_mode()
    def dense(self, image: torch.Tensor, out_hw: tuple[int, int]) -> torch.Tensor:
        """image [H,W,3] float RGB in [0,1] -> [h,w,D] float32 at out_hw = (h, w), on image's device."""
        if image.ndim != 3 or image.shape[-1] != 3:
            raise ValidationError("image", f"expected [H,W,3], got {tuple(image.shape)}")
        H, W = image.shape[:2]
        h, w = self.input_size(H, W)
        x = image.permute(2, 0, 1).unsqueeze(0).to(self.device, torch.float32)
        x = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
        x = (x - self.mean) / self.std
        tokens = self.model(pixel_values=x.to(self.dtype), **self.forward_kwargs).last_hidden_state
        gh, gw = h // self.patch, w // self.patch
        if tokens.shape[1] != self.skip + gh * gw:
            raise ValidationError(
                "model",
                f"{tokens.shape[1]} tokens for a {gh}x{gw} grid (expected {self.skip} before the patches)",
            )
        grid = tokens[0, self.skip :].float().reshape(gh, gw, self.dim).permute(2, 0, 1).unsqueeze(0)
        out = F.interpolate(grid, size=tuple(out_hw), mode="bilinear", align_corners=False)
        return out[0].permute(1, 2, 0).contiguous().to(image.device)


def load_dense_encoder(
    model_id: str = DEFAULT_DINO_ID,
    device: str | torch.device = "cpu",
    *,
    revision: str = DEFAULT_REVISION,
    offline: bool | str | None = None,
):
    """The dense regulariser of any id the registry knows: DINO or DINOv2 (``DinoEncoder.load``, at
    ``revision``), or the DINO stand-in (``standin-dino:FOLDER``, fmgs.features.standin_dino). Both offer
    ``dense``, ``id``, ``dim`` and ``files``."""

    if parse_encoder_id(model_id).family == "standin-dino":
        return load_standin_dino(model_id, device)
    return DinoEncoder.load(model_id, device=device, revision=revision, offline=offline)
