"""Small random-weight models of the architectures the product loads, saved as their hub folders."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import torch


def tiny_clip_model(vocab_size: int, dim: int = 16, seed: int = 1):
    """A CLIPModel with random weights: image 32 px, patch 8, ``dim``-D embeddings."""
    import transformers

    torch.manual_seed(seed)
    small = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2)
    cfg = transformers.CLIPConfig(
        text_config=dict(small, vocab_size=vocab_size, max_position_embeddings=77),
        vision_config=dict(small, image_size=32, patch_size=8),
        projection_dim=dim,
    )
    return transformers.CLIPModel(cfg).eval()


def save_clip_folder(model, folder: Path, bpe_dir: Path) -> Path:
    """``model`` saved as a hub folder: config.json, model.safetensors, CLIP's BPE tokenizer files and a
    preprocessor config."""
    model.save_pretrained(folder)
    for f in ("vocab.json", "merges.txt"):  # the untruncated merges list: the loader must cope
        shutil.copy(bpe_dir / f, folder / f)
    norm = {"image_mean": [0.5] * 3, "image_std": [0.25] * 3}
    (folder / "preprocessor_config.json").write_text(json.dumps(norm))
    return folder
