"""The segmenter stand-in (fmgs.features.standin_seg) and mask pooling (fmgs.features.segment_pool): the
sparse-graph segmentation and the pooling against their loop twins, save/load as shipped, and the
shipped weights giving the objects of an unseen scene segments of their own."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from fmgs.errors import ValidationError
from fmgs.features.segment_pool import pool_segments, pool_segments_reference, resize_segments
from fmgs.features.standin_seg import (
    SegStandinEncoder,
    SegStandinNet,
    affinity_segments,
    affinity_segments_reference,
    affinity_targets,
    load_standin_seg,
    object_segment_scores,
    save_standin_seg,
)

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = ROOT / "benchmarks" / "standin_seg"


def _config(**kw) -> dict:
    return {"width": 4, "short_side": 24, "mean": [0.5] * 3, "std": [0.25] * 3, "join": 0.5, **kw}


@pytest.mark.parametrize("seed", range(6))
def test_affinity_segments_match_the_flood_fill(seed):
    rng = np.random.default_rng(seed)
    h, w = rng.integers(1, 12, size=2)
    aff = rng.uniform(size=(2, h, w)).astype(np.float32) ** (seed % 3 + 0.5)  # sparse to dense joins
    for join, min_pixels in ((0.5, 1), (0.3, 3), (0.8, 2)):
        got = affinity_segments(aff, join, min_pixels)
        want = affinity_segments_reference(aff, join, min_pixels)
        np.testing.assert_array_equal(got, want)


def test_affinity_segments_of_the_true_affinities_are_the_label_components():
    lab = torch.tensor([[1, 1, 2, 2], [1, 3, 3, 2], [1, 3, 3, 2], [4, 4, 4, 4]])
    seg = affinity_segments(affinity_targets(lab[None])[0].numpy(), 0.5, 1)
    np.testing.assert_array_equal(seg, [[1, 1, 2, 2], [1, 3, 3, 2], [1, 3, 3, 2], [4, 4, 4, 4]])
    # one label in two pieces is two segments; a segment under min_pixels is 0
    lab = torch.tensor([[5, 0, 5, 5], [5, 0, 5, 5]])
    seg = affinity_segments(affinity_targets(lab[None])[0].numpy(), 0.5, 3)
    np.testing.assert_array_equal(seg, [[0, 0, 1, 1], [0, 0, 1, 1]])


def test_affinity_targets_ignore_the_last_row_and_column():
    t = affinity_targets(torch.tensor([[[1, 2], [1, 1]]]))
    np.testing.assert_array_equal(t[0, 0].numpy(), [[0, 0], [1, 0]])
    np.testing.assert_array_equal(t[0, 1].numpy(), [[1, 0], [0, 0]])


@pytest.mark.parametrize("seed", range(4))
def test_pool_segments_matches_its_loop_twin(seed):
    g = torch.Generator().manual_seed(seed)
    t = torch.randn(7, 9, 5, generator=g)
    t[0, 0] = 0.0  # a zero vector stays finite
    seg = torch.randint(0, 4, (7, 9), generator=g)
    got = pool_segments(t, seg)
    torch.testing.assert_close(got, pool_segments_reference(t, seg), atol=1e-6, rtol=1e-5)
    assert torch.isfinite(got).all()
    norms = got.norm(dim=-1)
    assert torch.allclose(norms[(seg > 0) | (t.norm(dim=-1) > 0)], torch.ones(()), atol=1e-5)


def test_pool_segments_outvotes_a_minority_inside_a_mask_and_keeps_the_outside():
    mug, floor = torch.tensor([1.0, 0.0]), torch.tensor([0.0, 1.0])
    t = floor.repeat(4, 4, 1)
    t[1:3, 1:3] = mug
    t[1, 1] = floor  # one crop of the mug named floor
    seg = torch.zeros(4, 4, dtype=torch.long)
    seg[1:3, 1:3] = 2
    out = pool_segments(t, seg)
    assert (out[1:3, 1:3] @ mug > 0.9).all()  # the mask's majority wins
    torch.testing.assert_close(out[0], t[0])  # id 0 keeps its own


def test_pool_segments_rejects_a_map_of_another_size_or_negative_ids():
    with pytest.raises(ValidationError, match="segments"):
        pool_segments(torch.ones(4, 4, 3), torch.zeros(4, 5, dtype=torch.long))
    with pytest.raises(ValidationError, match=">= 0"):
        pool_segments(torch.ones(2, 2, 3), -torch.ones(2, 2, dtype=torch.long))


def test_resize_segments_keeps_ids():
    seg = torch.tensor([[1, 2], [3, 0]])
    out = resize_segments(seg, (4, 4))
    assert set(out.unique().tolist()) == {0, 1, 2, 3} and out.dtype == torch.long
    assert resize_segments(seg, (2, 2)) is seg


def test_save_and_load_give_the_same_segments(tmp_path):
    torch.manual_seed(0)
    net = SegStandinNet(4)
    save_standin_seg(tmp_path, net, _config())
    enc = load_standin_seg(f"standin-seg:{tmp_path}")
    ref_net = SegStandinNet(4)
    ref_net.load_state_dict({k: v.half().float() for k, v in net.state_dict().items()})  # shipped float16
    ref = SegStandinEncoder(ref_net, _config(), "x")
    img = torch.rand(31, 41, 3)  # odd sides: padded, then cut back
    a = enc.affinity(img)
    assert a.shape == (2, 31, 41) and np.isfinite(a).all() and (a >= 0).all() and (a <= 1).all()
    np.testing.assert_allclose(a, ref.affinity(img), atol=1e-5)
    assert enc.segments(img).shape == (31, 41) and enc.files.files["standin_seg.safetensors"]
    with pytest.raises(ValidationError, match="image"):
        enc.affinity(torch.rand(4, 4))


def test_a_missing_folder_names_what_it_needs(tmp_path):
    from fmgs.features.models import ModelNotFoundError

    with pytest.raises(ModelNotFoundError, match=r"standin_seg\.json"):
        load_standin_seg(f"standin-seg:{tmp_path / 'nowhere'}")


def test_the_shipped_segmenter_gives_objects_segments_of_their_own(tmp_path):
    """On an unseen world scene most objects have a segment overlapping their mask by more than half,
    and most object pixels lie in a segment that is mostly their own object (the figures measured on the
    held-out scenes are in standin_seg.json)."""
    from PIL import Image

    from fmgs.synth import SynthConfig, generate

    cfg = json.loads((SHIPPED / "standin_seg.json").read_text())
    assert (SHIPPED / "standin_seg.safetensors").stat().st_size < 2**20
    seed = 7  # no training or held-out seed of the stand-ins
    assert seed not in cfg["train_seeds"] + cfg["heldout_seeds"]
    generate(tmp_path, SynthConfig(views=4, width=128, height=96, preset="world", objects=10, seed=seed))
    enc = load_standin_seg(f"standin-seg:{SHIPPED}")
    found, objects, own, total = 0, 0, 0, 0
    for p in sorted((tmp_path / "images").iterdir()):
        img = torch.from_numpy(np.asarray(Image.open(p).convert("RGB"), np.float32) / 255.0)
        lab = np.asarray(Image.open(tmp_path / "labels" / p.name)).astype(np.int64)
        ious, o, t = object_segment_scores(enc.segments(img), lab, np.unique(lab[lab >= 2]))
        found += sum(v > 0.5 for v in ious)
        objects += len(ious)
        own, total = own + o, total + t
    # 30 of 36 objects found and 0.894 of object pixels in their own segment when written (2026-11-30)
    assert found / objects > 0.6 and own / total > 0.6, (found, objects, own / total)


# The build's --segmenter option: targets.segmenter through the registry, the pyramid and the extraction.


def test_the_registry_knows_the_segmenter_and_refuses_other_ids(tmp_path):
    from fmgs.features.registry import parse_encoder_id, resolve_encoder
    from fmgs.features.standin_seg import load_segmenter

    save_standin_seg(tmp_path, SegStandinNet(4), _config())
    eid = f"standin-seg:{tmp_path}"
    assert parse_encoder_id(eid).family == "standin-seg"
    assert isinstance(load_segmenter(eid), SegStandinEncoder)
    assert resolve_encoder(eid).files["standin_seg.safetensors"]  # a build checks it before its first stage
    with pytest.raises(ValidationError, match="segmenter"):
        load_segmenter(f"standin-dino:{tmp_path}")


def test_a_segmenter_pools_the_blend_or_the_finest_scale_alone():
    from fmgs.build.config import TargetSpec
    from fmgs.build.pipeline import build_models

    spec = TargetSpec(segmenter="standin-seg:x", dino_model="standin-dino:y")
    assert spec.scale_blend == "dominant" and spec.segment_map == "blend"  # the default blend, pooled
    assert build_models(spec)["segmenter"] == "standin-seg:x"
    finest = TargetSpec(segmenter="standin-seg:x", dino_model="standin-dino:y", segment_map="finest")
    assert finest.scale_blend == "mean"  # one scale: nothing to blend
    with pytest.raises(ValueError, match="pools the finest scale alone"):
        TargetSpec(segmenter="standin-seg:x", segment_map="finest", scale_blend="dominant")
    with pytest.raises(ValueError, match="exclude each other"):
        TargetSpec(segmenter="standin-seg:x", segment_map="finest", single_scale=True)
    with pytest.raises(ValueError, match="segment_map"):
        TargetSpec(segmenter="standin-seg:x", segment_map="coarsest")


def test_the_finest_only_pyramid_gives_the_full_pyramids_finest_map():
    from fmgs.features.pyramid import pyramid_for, scale_maps

    class Enc:  # a deterministic embedding of a crop's mean colour
        image_size = 8

        def __call__(self, crops):
            return torch.cat([crops.mean((2, 3)), crops.std((2, 3))], 1)

    full, one = pyramid_for(Enc()), pyramid_for(Enc(), finest_only=True)
    assert one.scales == (min(full.scales),) and one.blend == "mean"
    img = torch.rand(30, 40, 3, generator=torch.Generator().manual_seed(0))
    a, b = scale_maps(Enc(), img, full, (15, 20)), scale_maps(Enc(), img, one, (15, 20))
    torch.testing.assert_close(a.maps[int(torch.tensor(a.edges).argmin())], b.maps[0])
    with pytest.raises(ValidationError, match="exclude each other"):
        pyramid_for(Enc(), single_scale=True, finest_only=True)


@pytest.fixture(scope="module")
def synth_scene(tmp_path_factory):
    from fmgs.synth import SynthConfig, generate

    out = tmp_path_factory.mktemp("synth_segments")
    generate(out, SynthConfig(views=2, width=32, height=24, points=500, supersample=1))
    return out


def test_extraction_pools_each_map_within_the_images_segments(synth_scene):
    """image_targets with a segmenter: the finest map pooled within the segments cut on the image, taken
    to the map's size by nearest neighbour (a fixed two-segment split here)."""
    from fmgs.data.dataset import load_dataset
    from fmgs.features.extract import ExtractConfig, image_targets
    from fmgs.features.pyramid import hybrid_map, pyramid_for

    class Enc:
        image_size, id, dim = 8, "test/mean-colour", 6

        def __call__(self, crops):
            return torch.cat([crops.mean((2, 3)), crops.std((2, 3)) + 0.1], 1)

    class Halves:  # left half one segment, right half another, one column in none
        def segments(self, image):
            H, W = image.shape[:2]
            seg = np.ones((H, W), np.int64)
            seg[:, W // 2 :] = 2
            seg[:, 0] = 0
            return seg

    ds = load_dataset(synth_scene)
    cfg = ExtractConfig(feature_scale=0.5, progress=False)
    pyr = pyramid_for(Enc(), finest_only=True)
    out = image_targets(ds, 0, Enc(), None, pyr, cfg, Halves())["clip"]
    image, _ = ds.image(0)
    h, w = out.shape[:2]
    plain = hybrid_map(Enc(), image, pyr, (h, w))
    seg = resize_segments(torch.from_numpy(Halves().segments(image)), (h, w))
    torch.testing.assert_close(out, pool_segments_reference(plain, seg), atol=1e-6, rtol=1e-5)
    right = out[:, w // 2 + 1 :].reshape(-1, 6)
    assert torch.allclose(right, right[:1].expand_as(right))  # one vector over the segment


def test_a_build_with_new_target_settings_starts_its_cache_and_field_over(tmp_path):
    """The feature cache resumes by file: adding a segmenter to a build that ran without one must not
    distil the old, unpooled maps."""
    from fmgs.build.config import TargetSpec
    from fmgs.build.pipeline import TARGETS_RECORD, restart_on_new_targets

    work = tmp_path / "work"

    def made() -> None:
        for d in ("features", "field"):
            (work / d).mkdir(parents=True, exist_ok=True)
            (work / d / "x").write_text("1")

    made()
    plain = TargetSpec(dino_model="standin-dino:y")
    assert not restart_on_new_targets(work, plain)  # no record yet: an older work folder is trusted
    assert (work / "features" / "x").is_file() and (work / TARGETS_RECORD).is_file()
    assert not restart_on_new_targets(work, plain)  # same settings: resumed
    assert (work / "field" / "x").is_file()
    pooled = TargetSpec(dino_model="standin-dino:y", segmenter="standin-seg:z")
    assert restart_on_new_targets(work, pooled)
    assert not (work / "features").exists() and not (work / "field").exists()
    made()
    assert not restart_on_new_targets(work, pooled)  # recorded: the next run resumes
    assert (work / "features" / "x").is_file()
