"""The crop pyramid's scales as a build setting (TargetSpec.crop_scales, ``--crop-scales``): validated,
carried from the flags to the pyramid the targets are cut with, and recorded so that a changed pyramid
starts the cache over while a work folder recorded before the setting existed resumes."""

from __future__ import annotations

import json

import pytest
import torch

from fmgs import cli
from fmgs.build.config import TargetSpec
from fmgs.commands.build import build_config
from fmgs.commands.features import target_spec
from fmgs.features.pyramid import PyramidConfig, pyramid_for, scale_maps
from fmgs.features.sizes import CROP_SCALES

FINER = (0.025, *CROP_SCALES)


class MeanColour:
    """A deterministic embedding of a crop: its mean colour and spread."""

    image_size, id, dim = 8, "test/mean-colour", 6

    def __call__(self, crops: torch.Tensor) -> torch.Tensor:
        return torch.cat([crops.mean((2, 3)), crops.std((2, 3)) + 0.1], 1)


def _args(*argv: str):
    return cli.build_parser().parse_args(list(argv))


def test_the_default_scales_are_the_pyramids():
    assert TargetSpec().crop_scales == CROP_SCALES == PyramidConfig().scales
    assert pyramid_for(MeanColour()).scales == CROP_SCALES


def test_crop_scales_flag_reaches_the_build_and_the_features_command(tmp_path):
    cfg = build_config(
        _args("build", "DATA", "--name", "n", "--crop-scales", "0.025,0.05,0.5", "--device", "cpu")
    )
    assert cfg.targets.crop_scales == (0.025, 0.05, 0.5)
    spec = target_spec(_args("features", "D", "--out", "O", "--crop-scales", "0.1"))
    assert spec.crop_scales == (0.1,)
    with pytest.raises(SystemExit):
        _args("build", "DATA", "--crop-scales", "0.05,fine")
    toml = tmp_path / "build.toml"
    toml.write_text('name = "n"\n[targets]\ncrop_scales = [0.025, 0.05]\n')
    cfg = build_config(_args("build", "DATA", "--config", str(toml), "--device", "cpu"))
    assert cfg.targets.crop_scales == (0.025, 0.05)  # a tuple, as the flag gives


@pytest.mark.parametrize(
    "scales, words",
    [
        ((), "one or more"),
        ((0.0, 0.05), r"in \(0, 1\]"),
        ((0.05, 1.5), r"in \(0, 1\]"),
        ((0.05, 0.05), "repeat"),
    ],
)
def test_bad_crop_scales_are_refused_by_name(scales, words):
    with pytest.raises(ValueError, match=f"crop_scales.*{words}"):
        TargetSpec(crop_scales=scales)


def test_the_single_scale_ablation_refuses_a_pyramid_it_would_ignore():
    assert TargetSpec(single_scale=True).crop_scales == CROP_SCALES
    with pytest.raises(ValueError, match=r"single_scale.*crop_scales"):
        TargetSpec(single_scale=True, crop_scales=FINER)


def test_a_finer_scale_adds_its_map_and_leaves_the_others_as_they_were():
    """The pyramid of FINER cuts the default's crops and one finer lattice more: every default scale's map
    is the same, and the finest map is the finer scale's."""
    enc = MeanColour()
    img = torch.rand(48, 64, 3, generator=torch.Generator().manual_seed(0))
    full = scale_maps(enc, img, pyramid_for(enc, scales=FINER), (24, 32))
    base = scale_maps(enc, img, pyramid_for(enc), (24, 32))
    assert len(full.maps) == len(base.maps) + 1 and full.crops > base.crops
    for a, b in zip(full.maps[1:], base.maps, strict=True):
        torch.testing.assert_close(a, b)
    assert min(full.edges) == full.edges[0] < min(base.edges)
    one = pyramid_for(enc, scales=FINER, finest_only=True)
    assert one.scales == (0.025,) and one.blend == "mean"  # segment pooling takes the finest given


def test_the_build_cuts_its_targets_with_the_given_scales(tmp_path, monkeypatch):
    """extract_features with crop_scales: the cached CLIP map is the hybrid map of exactly those scales."""
    from fmgs.build.pipeline import extract_features
    from fmgs.data.dataset import load_dataset
    from fmgs.features.pyramid import hybrid_map
    from fmgs.synth import SynthConfig, generate

    generate(tmp_path / "scene", SynthConfig(views=1, width=40, height=30, points=200, supersample=1))
    ds = load_dataset(tmp_path / "scene")
    spec = TargetSpec(clip_model="x", dino_model=None, crop_scales=(0.1, 0.4), feature_side=20)
    import fmgs.build.pipeline as pipeline

    loaded = []

    def load(model_id, device=None, revision=None):
        loaded.append(model_id)
        return MeanColour()

    monkeypatch.setattr(pipeline, "load_image_encoder", load)
    cache = extract_features(ds, tmp_path / "features", spec, "cpu", progress=False)
    assert loaded == ["x"]
    maps = cache.load(ds.frames[0].name).clip.float()
    image, _ = ds.image(0)
    want = hybrid_map(MeanColour(), image, PyramidConfig(scales=(0.1, 0.4), crop_px=8), tuple(maps.shape[:2]))
    torch.testing.assert_close(maps, want, atol=2e-3, rtol=2e-3)  # the cache stores float16
    other = hybrid_map(MeanColour(), image, PyramidConfig(crop_px=8), tuple(maps.shape[:2]))
    assert (maps - other).abs().max() > 1e-2  # the default pyramid's map is another


def test_a_record_made_before_crop_scales_existed_resumes_and_a_new_pyramid_restarts(tmp_path):
    from fmgs.build.pipeline import TARGETS_RECORD, restart_on_new_targets

    work = tmp_path / "work"
    (work / "features").mkdir(parents=True)
    (work / "features" / "x").write_text("1")
    spec = TargetSpec(dino_model="standin-dino:y")
    record = json.loads(json.dumps(spec.__dict__))
    del record["crop_scales"]  # how a build before the setting recorded its targets
    (work / TARGETS_RECORD).write_text(json.dumps(record))
    assert not restart_on_new_targets(work, spec)
    assert (work / "features" / "x").is_file()
    assert restart_on_new_targets(work, TargetSpec(dino_model="standin-dino:y", crop_scales=FINER))
    assert not (work / "features").exists()
    assert json.loads((work / TARGETS_RECORD).read_text())["crop_scales"] == list(FINER)
