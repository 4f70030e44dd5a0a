"""Region crops (benchmarks/region_crops.py): regions grown over a dense map, their crops and targets."""

from __future__ import annotations

import numpy as np
import torch

from benchmarks.region_crops import grow_regions, label_regions, region_boxes, region_target


def _two_blobs(h: int = 12, w: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    """A dense map [h,w,3]: background along e0, a 4x5 block along e1; and its label map."""
    d = torch.zeros(h, w, 3)
    d[..., 0] = 1.0
    lab = torch.zeros(h, w, dtype=torch.int64)
    d[3:7, 8:13] = torch.tensor([0.0, 1.0, 0.0])
    lab[3:7, 8:13] = 1
    return d, lab


def test_regions_follow_the_features():
    d, lab = _two_blobs()
    seg = grow_regions(d)
    assert len(np.unique(seg)) == 2 and (seg > 0).all()
    block = seg[lab.numpy() == 1]
    assert (block == block[0]).all() and block[0] != seg[0, 0]


def test_a_gradient_does_not_chain_two_regions():
    # a ramp from e0 to e1 across 20 columns: neighbours are all alike (cosine > 0.99), the ends are not
    t = torch.linspace(0, 1, 20)
    d = torch.stack([torch.cos(t * torch.pi / 2), torch.sin(t * torch.pi / 2), torch.zeros(20)], -1)
    seg = grow_regions(d.expand(6, 20, 3).clone())
    assert seg[0, 0] != seg[0, -1]


def test_small_regions_are_left_out():
    d, _ = _two_blobs()
    d[0, 0] = torch.tensor([0.0, 0.0, 1.0])  # one odd pixel
    seg = grow_regions(d, min_pixels=2)
    assert seg[0, 0] == 0 and (seg[1:] > 0).all()


def test_label_regions_split_components():
    lab = torch.zeros(8, 8, dtype=torch.int64)
    lab[0:2, 0:2] = 1
    lab[5:8, 5:8] = 1  # the same label twice, apart
    seg = label_regions(lab, min_pixels=4)
    assert len(np.unique(seg[lab.numpy() == 1])) == 2


def test_boxes_are_squares_on_the_longer_side_inside_the_image():
    seg = np.zeros((10, 20), np.int64)
    seg[0:2, 14:20] = 1  # 2 x 6 at the top right corner
    seg[4:9, 2:3] = 2  # 5 x 1
    boxes = dict(region_boxes(seg))
    assert boxes[1] == (14, 0, 20, 6)  # shifted down and left into the image
    x0, y0, x1, y1 = boxes[2]
    assert (x1 - x0, y1 - y0) == (5, 5) and y0 == 4 and x0 <= 2 < x1


def test_target_is_the_finest_outside_regions_and_the_mean_inside():
    h, w, D = 6, 8, 4
    seg = np.zeros((h, w), np.int64)
    seg[1:4, 1:4] = 1
    finest = torch.zeros(h, w, D)
    finest[..., 0] = 2.0
    crop_embedding = torch.tensor([0.0, 3.0, 0.0, 0.0])
    calls = []

    def embed(crops: torch.Tensor) -> torch.Tensor:
        calls.append(tuple(crops.shape))
        return crop_embedding.expand(len(crops), D)

    t = region_target(embed, torch.rand(h, w, 3), seg, finest, crop_px=5)
    assert calls == [(1, 3, 5, 5)]
    torch.testing.assert_close(t[0, 0], torch.tensor([1.0, 0.0, 0.0, 0.0]))
    r = 2**-0.5
    torch.testing.assert_close(t[2, 2], torch.tensor([r, r, 0.0, 0.0]))
    assert torch.isfinite(t).all()


def test_an_all_zero_map_gives_no_region_and_no_nan():
    seg = grow_regions(torch.zeros(5, 6, 8))
    assert (seg == 0).all()
    t = region_target(lambda c: torch.ones(len(c), 3), torch.rand(5, 6, 3), seg, torch.zeros(5, 6, 3), 4)
    assert torch.isfinite(t).all()


def test_a_masked_crop_shows_its_region_alone():
    """masked: the crop is black outside its region (LangSplat's masked crops); unmasked it is the image."""
    h, w = 6, 8
    seg = np.zeros((h, w), np.int64)
    seg[1, 1:4] = 1  # an L: its box (rows 1-3, columns 1-3) holds pixels of no region
    seg[2:4, 3] = 1
    image = torch.rand(h, w, 3) + 0.5  # no black pixel of its own
    seen = []

    def embed(crops: torch.Tensor) -> torch.Tensor:
        seen.append(crops.clone())
        return torch.ones(len(crops), 2)

    for masked in (False, True):
        region_target(embed, image, seg, torch.ones(h, w, 2), crop_px=3, masked=masked)
    plain, masked_crop = seen[0][0], seen[1][0]  # [3,3,3]: no resize at crop_px = the box's edge
    inside = torch.from_numpy(seg[1:4, 1:4] == 1)
    torch.testing.assert_close(plain, image[1:4, 1:4].permute(2, 0, 1))
    torch.testing.assert_close(masked_crop[:, inside], plain[:, inside])
    assert (masked_crop[:, ~inside] == 0).all() and (plain[:, ~inside] > 0).all()


def test_the_region_cache_holds_the_candidate_for_train_field(tmp_path):
    """``region_cache`` (the clip_path variant "region crops"): each frame's CLIP target is the region-crop
    target of the stand-ins' own maps, and the DINO target is the DINO stand-in's map, in the build's cache
    format, so ``fmgs train-field`` distils exactly the candidate."""
    from benchmarks.clip_path import STANDIN, STANDIN_DINO
    from benchmarks.region_crops import region_cache
    from fmgs.data.dataset import load_dataset
    from fmgs.features.cache import FeatureCache
    from fmgs.features.dino import load_dense_encoder
    from fmgs.features.pyramid import pyramid_for, scale_maps
    from fmgs.features.standin import load_standin
    from fmgs.synth import SynthConfig, generate

    data = tmp_path / "scene"
    generate(data, SynthConfig(views=2, width=64, height=48, objects=4, seed=5, points=3000, preset="world"))
    cache = FeatureCache.open(region_cache(data, tmp_path / "cache", STANDIN, STANDIN_DINO))
    ds = load_dataset(data)
    clip = load_standin(f"standin:{STANDIN}")
    dino = load_dense_encoder(f"standin-dino:{STANDIN_DINO}")
    image, _ = ds.image(1)
    with torch.inference_mode():
        sm = scale_maps(clip, image, pyramid_for(clip), (48, 64))
        dense = dino.dense(image, (48, 64))
        want = region_target(
            clip, image, grow_regions(dense), sm.maps[int(torch.tensor(sm.edges).argmin())], clip.image_size
        )
    got = cache.load(ds.frames[1].name)
    assert got.clip.shape == (48, 64, clip.dim) and got.dino.shape == dense.shape
    torch.testing.assert_close(got.clip, want, atol=2e-3, rtol=0)  # the cache stores float16
    torch.testing.assert_close(got.dino, dense, atol=2e-3, rtol=0)
    assert set(cache.entries) == {f.name for f in ds.frames}
