"""Fixtures of the feature tests."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def bpe_dir(data_dir):
    """CLIP's BPE tokenizer files (vocab.json, merges.txt) from the shared test data."""
    d = data_dir / "clip_tokenizer" / "hf_format"
    if not (d / "vocab.json").is_file():
        pytest.skip(f"CLIP tokenizer files not found in {d}")
    return d
