"""CLIP image embeddings (``CLIPModel.get_image_features``) with the model's preprocessing done in torch."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import torch
import torch.nn.functional as F

from fmgs.errors import ValidationError
from fmgs.features.models import DEFAULT_CLIP_ID, DEFAULT_REVISION, ModelFiles
from fmgs.features.registry import IMAGE_TYPES
from fmgs.features.standin import load_standin
from fmgs.features.text import ClipTextEncoder, embedding_dim, load_dual_encoder, pooled_output
from fmgs.vecmath import safe_normalize

CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
"""Per-channel RGB mean of CLIP's image normalisation (OpenAI and OpenCLIP alike)."""
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)
"""Per-channel RGB standard deviation of CLIP's image normalisation."""


class ImageEncoder(Protocol):
    """Embeds square RGB crops: what the hybrid CLIP pyramid needs from a model."""

    id: str
    """Identifier of the embedding space (the model id)."""
    dim: int
    """Embedding size D."""

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        """[B,3,S,S] float RGB in [0,1] -> [B,D] float32 unit-norm rows."""
        ...


class ClipImageEncoder:
    """The image tower and projection of a transformers dual encoder (``CLIPModel``, ``SiglipModel``, or an
    open_clip checkpoint mapped onto ``CLIPModel``), ``get_image_features`` L2-normalised.

    Inputs are resized straight to the model's square input size (no centre crop: the pyramid's crops are
    already square) with bicubic antialiased interpolation, then normalised with the model's mean/std.
    """

    def __init__(
        self,
        model: Any,
        model_id: str,
        device: str | torch.device = "cpu",
        mean: tuple[float, float, float] = CLIP_MEAN,
        std: tuple[float, float, float] = CLIP_STD,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        """Wrap an existing ``CLIPModel`` (moved to ``device``/``dtype`` and set to eval, in place).

        ``dtype`` (e.g. float16 on a GPU) is the model's compute type; outputs are float32.
        """
        self.device = torch.device(device)
        self.dtype = dtype
        self.model = model.to(self.device, dtype).eval()
        self.id = model_id
        self.files: ModelFiles | None = None
        """Where the weights came from, when loaded by id."""
        self.dim = embedding_dim(model.config)
        self.image_size = int(model.config.vision_config.image_size)
        self.mean = torch.tensor(mean, dtype=torch.float32, device=self.device).view(1, 3, 1, 1)
        self.std = torch.tensor(std, dtype=torch.float32, device=self.device).view(1, 3, 1, 1)

    @classmethod
    def load(
        cls,
        model_id: str = DEFAULT_CLIP_ID,
        model_dir: str | os.PathLike | None = None,
        device: str | torch.device = "cpu",
        dtype: torch.dtype = torch.float32,
        *,
        revision: str = DEFAULT_REVISION,
        offline: bool | str | None = None,
    ) -> ClipImageEncoder:
        """Load from ``model_dir``, the folder ``model_id``, the hub cache at ``revision``, or a download
        (fetch_model; ``offline`` forbids it).

        Mean/std come from the folder's ``preprocessor_config.json`` when it has them, else CLIP's.
        """
        model, _, (mean, std), files = _load_dual(model_id, model_dir, revision, offline)
        enc = cls(model, model_id, device, mean, std, dtype)
        enc.files = files
        return enc

    @torch.inference_mode()
    def encode_images(self, images: torch.Tensor) -> torch.Tensor:
        """[B,3,h,w] float RGB in [0,1] -> [B,D] float32 unit-norm rows on the encoder's device."""
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValidationError("images", f"expected [B,3,h,w], got {tuple(images.shape)}")
        x = images.to(self.device, torch.float32)
        S = self.image_size
        if x.shape[-2:] != (S, S):
            x = F.interpolate(x, size=(S, S), mode="bicubic", align_corners=False, antialias=True)
            x = x.clamp(0.0, 1.0)
        x = (x - self.mean) / self.std
        feats = pooled_output(self.model.get_image_features(pixel_values=x.to(self.dtype)))
        return safe_normalize(feats.float())

    __call__ = encode_images


class ClipEncoders(NamedTuple):
    """Image and text sides of one CLIP model (sharing its weights)."""

    image: ClipImageEncoder
    text: ClipTextEncoder


def load_image_encoder(
    model_id: str = DEFAULT_CLIP_ID,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
    *,
    revision: str = DEFAULT_REVISION,
    offline: bool | str | None = None,
) -> ImageEncoder:
    """The image encoder of any id the registry knows (fmgs.features.registry): a transformers CLIP or
    SigLIP (at ``revision``), an open_clip file, or the CLIP stand-in."""
    if model_id.startswith("standin:"):
        return load_standin(model_id, device)
    return ClipImageEncoder.load(model_id, device=device, dtype=dtype, revision=revision, offline=offline)


def load_clip(
    model_id: str = DEFAULT_CLIP_ID,
    model_dir: str | os.PathLike | None = None,
    device: str | torch.device = "cpu",
    *,
    revision: str = DEFAULT_REVISION,
) -> ClipEncoders:
    """Both encoders of one CLIP model, loaded once (fetched on first use, as fetch_model does)."""
    model, tokenizer, (mean, std), files = _load_dual(model_id, model_dir, revision)
    image = ClipImageEncoder(model, model_id, device, mean, std)
    text = ClipTextEncoder(model, tokenizer(), model_id, device)
    image.files = text.files = files
    return ClipEncoders(image, text)


def _load_dual(
    model_id: str,
    model_dir: str | os.PathLike | None,
    revision: str = DEFAULT_REVISION,
    offline: bool | str | None = None,
):
    """(model, tokenizer loader, (mean, std), ModelFiles) of a dual-encoder id (text.load_dual_encoder);
    an open_clip file normalises as CLIP does, a transformers model as its preprocessor config says."""

    model, tokenizer, files, openclip = load_dual_encoder(
        model_id, model_dir, offline, IMAGE_TYPES, "image encoder", revision=revision
    )
    norm = (CLIP_MEAN, CLIP_STD) if openclip else _preprocessor_mean_std(files.path)
    return model, tokenizer, norm, files


def _preprocessor_mean_std(d: Path) -> tuple[tuple[float, ...], tuple[float, ...]]:
    p = d / "preprocessor_config.json"
    if not p.is_file():
        return CLIP_MEAN, CLIP_STD
    try:
        cfg = json.loads(p.read_text())
        mean = tuple(float(v) for v in cfg.get("image_mean", CLIP_MEAN))
        std = tuple(float(v) for v in cfg.get("image_std", CLIP_STD))
    except (OSError, ValueError, TypeError) as e:
        raise ValidationError(str(p), f"cannot read image_mean/image_std ({e})") from e
    if len(mean) != 3 or len(std) != 3 or min(std) <= 0:
        raise ValidationError(str(p), f"bad image_mean {mean} / image_std {std}")
    return mean, std
