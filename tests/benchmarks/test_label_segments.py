"""Segment pooling with the label masks as segments (benchmarks/label_segments.py)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch


class _Masks:
    """A segmenter whose segments are a fixed map: what ``fmgs build --segmenter`` would pool with."""

    def __init__(self, seg: np.ndarray) -> None:
        self.seg = seg

    def segments(self, image: torch.Tensor) -> np.ndarray:
        assert tuple(image.shape[:2]) == self.seg.shape
        return self.seg


@pytest.mark.parametrize("segment_map", ["finest", "blend"])
def test_the_cache_is_the_build_pooling_within_the_label_masks(tmp_path, segment_map):
    """Each frame's CLIP target is what the build's own extraction (``image_targets`` with the pyramid the
    build uses for ``segment_map``) gives with a segmenter whose segments are the label components; the
    DINO target is the DINO stand-in's map; every pixel of a component shares one unit embedding."""
    from benchmarks.clip_path import STANDIN, STANDIN_DINO
    from benchmarks.label_segments import label_segments, label_segments_cache
    from fmgs.data.dataset import load_dataset
    from fmgs.features.cache import FeatureCache
    from fmgs.features.dino import load_dense_encoder
    from fmgs.features.extract import ExtractConfig, image_targets
    from fmgs.features.pyramid import pyramid_for
    from fmgs.features.sizes import SCALE_BLEND
    from fmgs.features.standin import load_standin
    from fmgs.synth import SynthConfig, generate

    data = tmp_path / "scene"
    generate(data, SynthConfig(views=2, width=64, height=48, objects=4, seed=5, points=3000, preset="world"))
    cache = FeatureCache.open(
        label_segments_cache(data, tmp_path / "cache", STANDIN, STANDIN_DINO, segment_map)
    )
    ds = load_dataset(data)
    names = json.loads((data / "scene.json").read_text())["label_names"]
    clip = load_standin(f"standin:{STANDIN}")
    dino = load_dense_encoder(f"standin-dino:{STANDIN_DINO}")
    finest = segment_map == "finest"
    pyramid = pyramid_for(clip, blend="mean" if finest else SCALE_BLEND, finest_only=finest)
    assert len(pyramid.scales) == (1 if finest else 7)
    for i, fr in enumerate(ds.frames):
        seg = label_segments(data, Path(fr.name).stem, names)
        with torch.inference_mode():
            want = image_targets(ds, i, clip, dino, pyramid, ExtractConfig(), _Masks(seg))
        got = cache.load(fr.name)
        assert got.clip.shape == want["clip"].shape == (48, 64, clip.dim)
        assert torch.isfinite(got.clip).all()
        torch.testing.assert_close(got.clip, want["clip"], atol=2e-3, rtol=0)  # the cache stores float16
        torch.testing.assert_close(got.dino, want["dino"], atol=2e-3, rtol=0)
        ids = np.unique(seg[seg > 0])
        assert len(ids) >= 3  # the floor, the backdrop and at least one object
        for k in ids:
            inside = got.clip[torch.from_numpy(seg == k)]
            assert (inside - inside[0]).abs().max() < 2e-3


def test_components_of_one_label_are_separate_segments(tmp_path):
    """Two parts of one label (an object split by an occluder) are two segments, as SAM masks them."""
    from PIL import Image

    from benchmarks.label_segments import label_segments

    lab = np.zeros((8, 12), np.uint8)
    lab[1:4, 1:4] = 2
    lab[1:4, 8:11] = 2
    lab[6:8, :] = 1
    (tmp_path / "labels").mkdir()
    Image.fromarray(lab).save(tmp_path / "labels" / "0000.png")
    seg = label_segments(tmp_path, "0000", ["background", "floor", "box"])
    assert seg[2, 2] != seg[2, 9] and seg[2, 2] > 0 and seg[2, 9] > 0
    assert len(np.unique(seg[lab == 2])) == 2 and len(np.unique(seg[lab == 1])) == 1


def test_an_unknown_segment_map_is_refused(tmp_path):
    from benchmarks.clip_path import STANDIN, STANDIN_DINO
    from benchmarks.label_segments import label_segments_cache

    with pytest.raises(ValueError, match="segment_map"):
        label_segments_cache(tmp_path, tmp_path / "c", STANDIN, STANDIN_DINO, "coarsest")
