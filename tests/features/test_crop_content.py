"""What a crop shows (fmgs.features.crop_content) and the oracle targets made from it
(benchmarks.clip_oracle)."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import torch

from fmgs.errors import ValidationError
from fmgs.features.crop_content import (
    STUFF_SALIENCE,
    caption_embeddings,
    caption_points,
    captions,
    window_shares,
    window_shares_reference,
)


class HashText:
    """A text encoder with a fixed random unit vector per string (no model needed)."""

    dim = 32

    def encode_text(self, texts: list[str]) -> torch.Tensor:
        rows = []
        for t in texts:
            g = torch.Generator().manual_seed(int(hashlib.sha256(t.encode()).hexdigest()[:8], 16))
            rows.append(torch.nn.functional.normalize(torch.randn(self.dim, generator=g), dim=0))
        return torch.stack(rows)


@pytest.mark.parametrize("side", [1, 4, 7, 20])
def test_window_shares_match_the_crop_by_crop_twin(side):
    rng = np.random.default_rng(side)
    labels = rng.integers(0, 5, size=(24, 31))
    labels[5:15, 8:20] = 3  # a block, so shares are not all alike
    ys = np.unique(rng.integers(0, 24 - side + 1, size=6))
    xs = np.unique(rng.integers(0, 31 - side + 1, size=7))
    fast = window_shares(labels, side, ys, xs, 6)
    ref = window_shares_reference(labels, side, ys, xs, 6)
    assert fast.shape == (len(ys), len(xs), 6)
    np.testing.assert_allclose(fast, ref, atol=1e-12)
    np.testing.assert_allclose(fast.sum(-1), 1.0, atol=1e-12)


def test_window_shares_weigh_the_centre_most():
    labels = np.zeros((9, 9), np.int64)
    labels[3:6, 3:6] = 1  # the middle ninth of a 9x9 crop
    s = window_shares(labels, 9, np.array([0]), np.array([0]), 2)[0, 0]
    assert s[1] > 2 / 9  # the window gives the middle ninth more than twice its area (uniform: 1/9)


def test_window_shares_name_bad_input():
    labels = np.zeros((8, 8), np.int64)
    with pytest.raises(ValidationError, match="side"):
        window_shares(labels, 9, np.array([0]), np.array([0]), 1)
    with pytest.raises(ValidationError, match="labels"):
        window_shares(labels + 3, 4, np.array([0]), np.array([0]), 2)


def test_a_crop_of_one_object_is_its_caption_mixture_and_stuff_counts_less():
    names = ["background", "floor", "red striped cube"]
    assert [c for c, _ in captions(names[2])] == ["red striped cube", "red cube", "cube"]
    text = HashText()
    points = caption_points(names, text)
    caps = text.encode_text(["red striped cube", "red cube", "cube"])
    want = torch.nn.functional.normalize(0.5 * caps[0] + 0.3 * caps[1] + 0.2 * caps[2], dim=0)
    only = caption_embeddings(torch.tensor([[0.0, 0.0, 1.0]]), names, points)[0]
    torch.testing.assert_close(only, want)
    half = caption_embeddings(torch.tensor([[0.0, 0.5, 0.5]]), names, points)[0]
    w_obj = 0.5 / (0.5 + STUFF_SALIENCE * 0.5)  # the object's salient weight
    mixed = w_obj * points[2] + (1 - w_obj) * points[1]
    torch.testing.assert_close(half, torch.nn.functional.normalize(mixed, dim=0))


@pytest.mark.parametrize("blend", ["mean", "dominant"])
def test_oracle_targets_name_a_small_object_at_its_middle(blend):
    from benchmarks.clip_oracle import oracle_map
    from fmgs.features.pyramid import PyramidConfig

    names = ["background", "floor", "red striped cube", "blue ball", "wall"]
    labels = np.ones((48, 64), np.int64)
    labels[20:30, 28:38] = 2  # a tenth of the short side: smaller than most crops
    labels[5:25, 2:22] = 3
    dense = torch.zeros(24, 32, 8)
    dense[..., 0] = 1.0
    dense[10:15, 14:19] = torch.nn.functional.one_hot(torch.tensor(1), 8).float()  # DINO sees the cube apart
    text = HashText()
    cfg = PyramidConfig(blend=blend, crop_px=32)
    m = oracle_map(
        labels, names, caption_points(names, text), cfg, (24, 32), dense if blend != "mean" else None
    )
    assert m.shape == (24, 32, HashText.dim) and torch.isfinite(m).all()
    torch.testing.assert_close(m.norm(dim=-1), torch.ones(24, 32))
    table = text.encode_text(names[1:4])
    pred = (m @ table.T).argmax(-1) + 1
    assert pred[12, 16] == 2 and pred[7, 6] == 3 and pred[22, 2] == 1
