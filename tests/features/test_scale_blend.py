"""Blending the pyramid's scales (fmgs.features.scale_blend): the box mean against its loop twin, the
coherence as a region's share of a box, each blend's weights, and the blend keeping a small object the
equal mean loses."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from fmgs.errors import ValidationError
from fmgs.features.pyramid import PyramidConfig, hybrid_map
from fmgs.features.scale_blend import (
    blend_scales,
    box_mean,
    box_mean_reference,
    coherence,
    pool_regions,
    scale_weights,
)


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 9), st.integers(1, 9), st.integers(0, 6), st.integers(0, 2**31 - 1))
def test_box_mean_equals_its_loop_twin(h, w, r, seed):
    x = torch.randn(h, w, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    torch.testing.assert_close(box_mean(x, r), box_mean_reference(x, r), rtol=1e-12, atol=1e-12)


def test_coherence_is_the_regions_share_of_the_box():
    """One-hot DINO vectors per region: c_s(p) is the share of p's region in the box about p."""
    lab = torch.zeros(12, 16, dtype=torch.long)
    lab[4:8, 6:10] = 1  # a 4x4 object on a background
    dense = torch.nn.functional.one_hot(lab, 2).double() * 3.0  # not unit: coherence normalises
    c = coherence(dense, [1.0, 3.0, 5.0])
    assert torch.equal(c[0], torch.ones(12, 16, dtype=c.dtype))
    assert c[1, 5, 7] == pytest.approx(1.0)  # a 3x3 box inside the object
    assert c[2, 5, 7] == pytest.approx(16 / 25)  # 5x5 box rows 3..7, cols 5..9: 4x4 of the object
    assert c[2, 0, 0] == pytest.approx(1.0)  # shifted inside the image, all background
    assert float(c.min()) >= 0.0


def test_weights_of_each_blend():
    lab = torch.zeros(10, 10, dtype=torch.long)
    lab[4:6, 4:6] = 1
    dense = torch.nn.functional.one_hot(lab, 2).float()
    edges = [1.0, 3.0, 9.0]
    assert scale_weights("mean", None, edges) is None
    w = scale_weights("coherence", dense, edges)
    assert w.shape == (3, 10, 10) and torch.allclose(w[:, 4, 4], torch.tensor([1.0, 4 / 9, 4 / 81]))
    d = scale_weights("dominant", dense, edges)
    assert d[:, 4, 4].tolist() == [1.0, 0.0, 0.0] and d[:, 0, 0].tolist() == [1.0, 1.0, 1.0]
    with pytest.raises(ValidationError, match="needs the dense"):
        scale_weights("coherence", None, edges)
    with pytest.raises(ValidationError, match="must be one of"):
        scale_weights("median", dense, edges)


def test_blend_with_equal_weights_is_the_mean():
    maps = [torch.randn(5, 6, 4) for _ in range(3)]
    torch.testing.assert_close(blend_scales(maps, torch.ones(3, 5, 6)), blend_scales(maps, None))
    out = blend_scales(maps, torch.rand(3, 5, 6) + 0.1)
    torch.testing.assert_close(out.norm(dim=-1), torch.ones(5, 6))


def _small_object_image():
    """A 48x64 image: a red 6x6 square on grey, and its label map."""
    img = torch.full((48, 64, 3), 0.5)
    img[20:26, 28:34] = torch.tensor([0.9, 0.1, 0.1])
    lab = torch.zeros(48, 64, dtype=torch.long)
    lab[20:26, 28:34] = 1
    return img, lab


def test_coherence_blend_keeps_a_small_object_the_equal_mean_loses():
    """An encoder that names what a crop mostly shows (red where red is the majority): at the object's
    pixels the coarse crops say grey, so the equal mean of seven scales says grey; weighing each scale by
    how much of its crop is the pixel's region (DINO: here the colour) keeps red."""
    img, lab = _small_object_image()
    red, grey = torch.tensor([1.0, 0.0]), torch.tensor([0.0, 1.0])

    def majority(crops):  # [B,3,S,S] -> what most of the crop is
        redness = (crops[:, 0] - crops[:, 1] > 0.4).float().mean((1, 2))
        return torch.where((redness > 0.5)[:, None], red, grey)

    dense = torch.nn.functional.one_hot(lab, 2).float()
    cfg = PyramidConfig(crop_px=8)
    with pytest.raises(ValidationError, match="needs the dense"):
        hybrid_map(majority, img, PyramidConfig(crop_px=8, blend="coherence"), (48, 64))
    mean = hybrid_map(majority, img, cfg, (48, 64))
    coh = hybrid_map(majority, img, PyramidConfig(crop_px=8, blend="coherence"), (48, 64), dense=dense)
    inner = torch.zeros_like(lab, dtype=torch.bool)
    inner[21:25, 29:33] = True  # its rim blends with the floor in every scale's interpolation
    assert float((mean[inner] @ red > mean[inner] @ grey).float().mean()) == 0.0
    assert float((coh[inner] @ red > coh[inner] @ grey).float().mean()) == 1.0
    far = torch.ones_like(inner)
    far[17:29, 25:37] = False
    assert float((coh[far] @ grey > coh[far] @ red).float().mean()) == 1.0


def test_pool_regions_averages_within_a_region_only():
    lab = torch.zeros(8, 8, dtype=torch.long)
    lab[:, 4:] = 1
    dense = torch.nn.functional.one_hot(lab, 2).float()
    target = torch.randn(8, 8, 5)
    out = pool_regions(target, dense, radius=8)  # the window covers the image
    for r in (0, 1):
        want = torch.nn.functional.normalize(target[lab == r].mean(0), dim=-1)
        torch.testing.assert_close(out[lab == r], want.expand(int((lab == r).sum()), 5), atol=1e-5, rtol=1e-5)
