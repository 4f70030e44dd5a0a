"""CLIP's tokenizer from the files beside a model, offline: one loader for the transformers CLIP models
(fmgs.features.text) and the open_clip checkpoints mapped onto them (fmgs.features.openclip)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from fmgs.features.models import ModelNotFoundError, require_transformers


def clip_tokenizer_from_bpe_files(vocab_json: str | os.PathLike, merges_txt: str | os.PathLike) -> Any:
    """A ``transformers.CLIPTokenizer`` from CLIP's ``vocab.json`` + ``merges.txt``, offline.

    Only merges whose result is in the vocabulary are kept: CLIP uses the first
    ``len(vocab) - 2*256 - 2`` merges and some distributions ship the untruncated list.
    """
    transformers = require_transformers()
    vocab = json.loads(Path(vocab_json).read_text(encoding="utf-8"))
    merges = []
    with open(merges_txt, encoding="utf-8") as f:
        for line in f:
            parts = line.rstrip("\n").split(" ")
            if line.startswith("#version") or len(parts) != 2:
                continue
            if parts[0] + parts[1] in vocab:
                merges.append((parts[0], parts[1]))
    return transformers.CLIPTokenizer(vocab=vocab, merges=merges)


def load_clip_tokenizer(model_dir: str | os.PathLike) -> Any:
    """The tokenizer saved beside a CLIP model: ``tokenizer.json`` if any, else vocab.json + merges.txt."""
    d = Path(model_dir)
    if (d / "tokenizer.json").is_file():
        return require_transformers().AutoTokenizer.from_pretrained(str(d), local_files_only=True)
    if (d / "vocab.json").is_file() and (d / "merges.txt").is_file():
        return clip_tokenizer_from_bpe_files(d / "vocab.json", d / "merges.txt")
    raise ModelNotFoundError(str(d), [f"{d} (no tokenizer.json, no vocab.json + merges.txt)"], "tokenizer")
