"""Shared fixtures: data location, hypothesis profiles, seeding (helpers live in ``tests.helpers``)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch
from hypothesis import HealthCheck, settings

settings.register_profile(
    "default", max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.register_profile(
    "thorough", max_examples=600, deadline=None, suppress_health_check=list(HealthCheck)
)
settings.load_profile(os.environ.get("FMGS_HYPOTHESIS_PROFILE", "default"))

# Tests never download models: the ones that test downloads turn this off against a local hub server.
os.environ["FMGS_OFFLINE"] = "1"

# Without a GPU, the triton backend's kernel runs in Triton's interpreter (tests/render/test_triton_blend.py);
# the variable must be set before triton is first imported.
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")

DATA_DIR = Path(os.environ.get("FMGS_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """../shared/data (or $FMGS_DATA); tests that need it skip with the reason when it is absent."""
    if not DATA_DIR.is_dir():
        pytest.skip(f"test data not found at {DATA_DIR} (set FMGS_DATA)")
    return DATA_DIR


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)


@pytest.fixture(scope="module")
def bpe_dir(data_dir):
    """CLIP's BPE tokenizer files (vocab.json, merges.txt) from the shared test data."""
    d = data_dir / "clip_tokenizer" / "hf_format"
    if not (d / "vocab.json").is_file():
        pytest.skip(f"CLIP tokenizer files not found in {d}")
    return d
