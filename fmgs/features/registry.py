"""Encoder ids and the model families they name: the one place an id becomes a loader.

An id says where a model comes from; the model's own config says what it is.

- ``sentence-transformers/all-MiniLM-L6-v2``: MiniLM from its wheel (the label-name text encoder).
- ``hf:ORG/NAME``, ``ORG/NAME`` or a folder: a transformers model, fetched on first use
  (fmgs.features.models). Its config.json ``model_type`` picks the wrapper: ``clip`` and ``siglip``
  (image and text towers), ``vit`` (DINO), ``dinov2`` and ``dinov2_with_registers`` (DINOv2).
- ``openclip-file:PATH``: an open_clip checkpoint file (``open_clip_model.safetensors``; the pickled
  ``.bin`` is refused) mapped onto the transformers CLIP architecture (fmgs.features.openclip), GELU blocks
  as the LAION models have; ``openclip-file+quickgelu:PATH`` for OpenAI-trained checkpoints.
- ``standin:FOLDER``: the CLIP stand-in trained into MiniLM's text space (fmgs.features.standin): an
  image encoder whose scenes are queried with MiniLM.
- ``standin-dino:FOLDER``: the DINO stand-in trained without labels (fmgs.features.standin_dino): a
  dense regulariser.

Scenes and feature caches record the id as given, so queries load the same model the same way.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from fmgs.errors import ValidationError
from fmgs.features.models import MINILM_ID

HF = "hf:"
OPENCLIP_FILE = "openclip-file:"
OPENCLIP_FILE_QUICKGELU = "openclip-file+quickgelu:"
STANDIN = "standin:"
STANDIN_DINO = "standin-dino:"
TEXT_TYPES = ("clip", "siglip")
"""transformers ``model_type``s with a text tower our text encoder wraps."""
IMAGE_TYPES = ("clip", "siglip")
"""``model_type``s with an image tower and projection the CLIP pyramid can use."""
DENSE_TYPES = ("vit", "dinov2", "dinov2_with_registers")
"""``model_type``s whose patch tokens make the DINO regulariser's dense map."""


@dataclass(frozen=True)
class EncoderRef:
    """A parsed encoder id."""

    family: str
    """"minilm", "hf", "openclip-file", "standin" or "standin-dino"."""
    ref: str
    """The hub model id or folder (hf), the checkpoint path (openclip-file), or MiniLM's id."""
    quick_gelu: bool = False
    """openclip-file only: the checkpoint's blocks use QuickGELU (OpenAI-trained CLIP)."""


def parse_encoder_id(encoder_id: str) -> EncoderRef:
    """The family and reference an encoder id names (see the module docstring)."""
    if not isinstance(encoder_id, str) or not encoder_id.strip():
        raise ValidationError("encoder id", f"expected a non-empty string, got {encoder_id!r}")
    if encoder_id == MINILM_ID:
        return EncoderRef("minilm", encoder_id)
    for prefix, quick in ((OPENCLIP_FILE_QUICKGELU, True), (OPENCLIP_FILE, False)):
        if encoder_id.startswith(prefix):
            path = encoder_id[len(prefix) :]
            if not path:
                raise ValidationError("encoder id", f"{encoder_id!r} names no checkpoint file")
            return EncoderRef("openclip-file", path, quick)
    for prefix, family in ((STANDIN, "standin"), (STANDIN_DINO, "standin-dino")):
        if encoder_id.startswith(prefix):
            path = encoder_id[len(prefix) :]
            if not path:
                raise ValidationError("encoder id", f"{encoder_id!r} names no folder")
            return EncoderRef(family, path)
    if encoder_id.startswith(HF):
        ref = encoder_id[len(HF) :]
        if not ref:
            raise ValidationError("encoder id", f"{encoder_id!r} names no model")
        return EncoderRef("hf", ref)
    return EncoderRef("hf", encoder_id)


def model_type(folder: Path) -> str:
    """The ``model_type`` of a transformers model folder's config.json."""
    try:
        return str(json.loads((Path(folder) / "config.json").read_text())["model_type"])
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValidationError(str(folder), f"config.json gives no model_type ({e})") from e


def require_type(folder: Path, encoder_id: str, allowed: tuple[str, ...], role: str) -> str:
    """``model_type(folder)`` when it is one of ``allowed``; else an error naming the role and the types."""
    kind = model_type(folder)
    if kind not in allowed:
        raise ValidationError(
            encoder_id, f"a {kind!r} model cannot serve as the {role}; supported: {', '.join(allowed)}"
        )
    return kind
