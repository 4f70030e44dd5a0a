"""SAM as the segmenter (fmgs.features.sam): mask painting against its pixel-by-pixel twin, the stability
score, and a SAM of random weights built from a small config of its own architecture, loaded by folder
as a user's download would be, against the model called directly."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fmgs.errors import ValidationError
from fmgs.features.sam import SamMaskConfig, paint_masks, paint_masks_reference, stability_score


def _transformers():
    """transformers, which SAM needs (the mask painting does not)."""
    return pytest.importorskip("transformers", reason="in requirements/cpu.txt (CI)")


@pytest.mark.parametrize("seed", range(5))
def test_paint_masks_matches_the_pixel_by_pixel_twin(seed):
    rng = np.random.default_rng(seed)
    n, h, w = int(rng.integers(0, 6)), int(rng.integers(1, 9)), int(rng.integers(1, 9))
    masks = rng.uniform(size=(n, h, w)) < rng.uniform(0.1, 0.7, size=(n, 1, 1))
    for min_pixels in (1, 3):
        np.testing.assert_array_equal(
            paint_masks(masks, min_pixels), paint_masks_reference(masks, min_pixels)
        )


def test_a_small_mask_paints_over_the_large_one_it_lies_on():
    big = np.zeros((4, 6), bool)
    big[:, :4] = True
    small = np.zeros((4, 6), bool)
    small[1:3, 1:3] = True
    seg = paint_masks(np.stack([small, big]), 1)
    np.testing.assert_array_equal(
        seg, [[1, 1, 1, 1, 0, 0], [1, 2, 2, 1, 0, 0], [1, 2, 2, 1, 0, 0], [1, 1, 1, 1, 0, 0]]
    )
    with pytest.raises(ValidationError, match="masks"):
        paint_masks(np.zeros((4, 6), bool))
    for none in (np.zeros((0, 4, 6), bool), np.zeros((2, 4, 6), bool)):  # no mask, or empty ones
        assert (paint_masks(none) == 0).all() and (paint_masks_reference(none) == 0).all()


def test_stability_score():
    lg = torch.tensor([[[3.0, 0.5], [-0.5, -3.0]]])  # above +1: one pixel; above -1: three
    torch.testing.assert_close(stability_score(lg, 1.0), torch.tensor([1 / 3]))
    assert stability_score(torch.full((1, 2, 2), -5.0), 1.0).item() == 1.0  # empty: stable


@pytest.fixture(scope="module")
def tiny_sam(tmp_path_factory):
    transformers = _transformers()
    from transformers.models.sam.configuration_sam import (
        SamMaskDecoderConfig,
        SamPromptEncoderConfig,
        SamVisionConfig,
    )

    vision = SamVisionConfig(hidden_size=32, num_hidden_layers=2, num_attention_heads=2, image_size=64,
                             patch_size=8, output_channels=16, mlp_dim=64, global_attn_indexes=[1],
                             window_size=4, num_pos_feats=8)  # fmt: skip
    prompt = SamPromptEncoderConfig(hidden_size=16, image_size=64, patch_size=8, mask_input_channels=4)
    decoder = SamMaskDecoderConfig(hidden_size=16, num_attention_heads=2, mlp_dim=32, iou_head_hidden_dim=16)
    cfg = transformers.SamConfig(vision_config=vision.to_dict(), prompt_encoder_config=prompt.to_dict(),
                                 mask_decoder_config=decoder.to_dict())  # fmt: skip
    torch.manual_seed(0)
    folder = tmp_path_factory.mktemp("tiny_sam")
    transformers.SamModel(cfg).save_pretrained(folder)
    ip = transformers.SamImageProcessor(size={"longest_edge": 64}, pad_size={"height": 64, "width": 64},
                                        mask_size={"longest_edge": 16},
                                        mask_pad_size={"height": 16, "width": 16})  # fmt: skip
    transformers.SamProcessor(image_processor=ip).save_pretrained(folder)
    return folder


def test_sam_by_folder_keeps_each_points_best_mask_as_the_model_gives_it(tiny_sam):
    from fmgs.features.standin_seg import load_segmenter

    transformers = _transformers()
    keep_all = SamMaskConfig(points_per_side=3, points_per_batch=4, pred_iou=-1e9, stability=-1.0)
    seg = load_segmenter(str(tiny_sam))
    seg.cfg = keep_all
    img = torch.rand(24, 32, 3, generator=torch.Generator().manual_seed(1))
    masks, scores = seg.masks(img)
    assert masks.shape == (9, 24, 32) and masks.dtype == bool and np.isfinite(scores).all()
    # the model called directly, one point at a time: the best of its three masks, at the image's size
    model = transformers.SamModel.from_pretrained(str(tiny_sam)).eval()
    proc = transformers.SamProcessor.from_pretrained(str(tiny_sam)).image_processor
    rgb = (img * 255).round().to(torch.uint8).numpy()
    inp = proc(images=rgb, return_tensors="pt")
    rh, rw = (int(v) for v in inp["reshaped_input_sizes"][0])
    with torch.inference_mode():
        for k, (y, x) in enumerate((y, x) for y in range(3) for x in range(3)):
            p = torch.tensor([[[[(x + 0.5) / 3 * rw, (y + 0.5) / 3 * rh]]]])
            out = model(
                pixel_values=inp["pixel_values"], input_points=p, input_labels=torch.ones(1, 1, 1).long()
            )
            lg = proc.post_process_masks(out.pred_masks, inp["original_sizes"], inp["reshaped_input_sizes"],
                                         binarize=False)[0][0]  # fmt: skip
            best = int(out.iou_scores[0, 0].argmax())
            assert (masks[k] == (lg[best] > 0).numpy()).mean() > 0.999, k
            assert scores[k] == pytest.approx(float(out.iou_scores[0, 0, best]), abs=1e-5)
    s = seg.segments(img)
    assert s.shape == (24, 32) and s.dtype == np.int64 and s.min() >= 0
    assert set(np.unique(s[s > 0])) == set(range(1, int(s.max()) + 1))  # ids 1..n
    strict = SamMaskConfig(points_per_side=3, pred_iou=2.0)  # no predicted IoU reaches 2: nothing kept
    seg.cfg = strict
    assert seg.masks(img)[0].shape == (0, 24, 32) and (seg.segments(img) == 0).all()


def test_a_model_of_another_kind_is_refused_as_the_segmenter(tmp_path):
    from fmgs.features.standin_seg import load_segmenter

    transformers = _transformers()
    cfg = transformers.ViTConfig(hidden_size=16, num_hidden_layers=1, num_attention_heads=2,
                                 intermediate_size=16, image_size=32, patch_size=8)  # fmt: skip
    transformers.ViTModel(cfg).save_pretrained(tmp_path)
    with pytest.raises(ValidationError, match="cannot serve as the segmenter"):
        load_segmenter(str(tmp_path))


def test_sam_is_fetched_from_the_hub_on_first_use_then_loads_offline(tiny_sam, tmp_path, monkeypatch):
    """The way a user's build meets it: ``--segmenter ORG/NAME`` downloads SAM (weights, config and the
    image processor's settings) through the product's fetch, against a local hub; later runs load it
    from the cache with downloads off."""
    pytest.importorskip("huggingface_hub", reason="in requirements/cpu.txt (CI)")
    from fmgs.features.standin_seg import load_segmenter
    from tests.helpers.hub_server import HubRepo, HubServer

    with HubServer([HubRepo.from_folder("acme/tiny-sam", tiny_sam)]) as server:
        monkeypatch.setenv("HF_ENDPOINT", server.endpoint)
        monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hub-cache"))
        monkeypatch.setenv("FMGS_HUB_TIMEOUT", "2")
        for k in ("FMGS_OFFLINE", "HF_HUB_OFFLINE"):
            monkeypatch.delenv(k, raising=False)
        seg = load_segmenter("acme/tiny-sam")
        assert seg.files is not None and seg.files.source == "download"
        names = {p.name for p in seg.files.path.iterdir()}  # the image processor's settings came too
        assert names & {"preprocessor_config.json", "processor_config.json"}, names
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")  # the server is gone: the cache alone
    again = load_segmenter("acme/tiny-sam")
    assert again.files.source == "cache"
    img = torch.rand(24, 32, 3, generator=torch.Generator().manual_seed(2))
    again.cfg = seg.cfg = SamMaskConfig(points_per_side=2, pred_iou=-1e9, stability=-1.0)
    np.testing.assert_array_equal(again.segments(img), seg.segments(img))
