"""The pooled CLIP targets of the `dominant pooled` variant (benchmarks/clip_variants.py: pooled_cache)."""

from __future__ import annotations

import torch


def test_the_cache_is_the_build_blend_pooled_within_dino_neighbourhoods(tmp_path):
    """Each frame's CLIP target is the build's own extraction (``image_targets`` with the default pyramid)
    pooled by ``pool_regions`` over the radius the target maps' "+ pooled" candidates use, with the DINO
    stand-in's map that the cache also holds as the DINO target; the pooled map is unit-norm, finite and
    not the unpooled one."""
    from benchmarks.clip_path import STANDIN, STANDIN_DINO
    from benchmarks.clip_targets import POOL_RADIUS
    from benchmarks.clip_variants import VARIANTS, pooled_cache
    from fmgs.data.dataset import load_dataset
    from fmgs.features.cache import FeatureCache
    from fmgs.features.dino import load_dense_encoder
    from fmgs.features.extract import ExtractConfig, image_targets
    from fmgs.features.pyramid import pyramid_for
    from fmgs.features.scale_blend import pool_regions
    from fmgs.features.standin import load_standin
    from fmgs.synth import SynthConfig, generate

    data = tmp_path / "scene"
    generate(data, SynthConfig(views=1, width=64, height=48, objects=4, seed=6, points=3000, preset="world"))
    blend = VARIANTS["dominant pooled"]["blend"]
    cache = FeatureCache.open(pooled_cache(data, tmp_path / "cache", STANDIN, STANDIN_DINO, blend))
    ds = load_dataset(data)
    clip = load_standin(f"standin:{STANDIN}")
    dino = load_dense_encoder(f"standin-dino:{STANDIN_DINO}")
    pyramid = pyramid_for(clip, blend=blend)
    radius = round(POOL_RADIUS * 48)
    assert radius >= 2  # a neighbourhood wider than the pixel itself
    for i, fr in enumerate(ds.frames):
        with torch.inference_mode():
            built = image_targets(ds, i, clip, dino, pyramid, ExtractConfig())
            want = pool_regions(built["clip"], built["dino"], radius)
        got = cache.load(fr.name)
        assert got.clip.shape == want.shape == (48, 64, clip.dim)
        assert torch.isfinite(got.clip).all()
        torch.testing.assert_close(got.clip, want, atol=2e-3, rtol=0)  # the cache stores float16
        torch.testing.assert_close(got.dino, built["dino"], atol=2e-3, rtol=0)
        torch.testing.assert_close(got.clip.float().norm(dim=-1), torch.ones(48, 64), atol=2e-3, rtol=0)
        assert (got.clip.float() - built["clip"]).abs().max() > 0.05  # pooling moved the targets


def test_the_variant_makes_its_cache_then_distils_it_with_dino_and_dotsim(tmp_path, monkeypatch):
    """``clip_build`` of "dominant pooled" writes ``pooled_cache`` for the default blend once, then
    ``fmgs train-field`` distils that cache with the default's loss (DINO target and dotsim)."""
    import benchmarks.clip_variants
    import fmgs.cli
    from benchmarks.clip_variants import STANDIN, STANDIN_DINO, clip_build
    from fmgs.features.sizes import SCALE_BLEND

    calls: list[list[str]] = []
    monkeypatch.setattr(fmgs.cli, "main", lambda cmd: calls.append(cmd) or 0)
    made: list[tuple] = []

    def cache(data, cache_dir, standin, dino, blend):
        cache_dir.mkdir(parents=True)
        made.append((cache_dir, blend))

    monkeypatch.setattr(benchmarks.clip_variants, "pooled_cache", cache)
    data = tmp_path / "scene-7"
    pkg = clip_build(tmp_path, 7, data, "dominant pooled", 1500, STANDIN, STANDIN_DINO, 1)
    features = tmp_path / "models" / ".work" / "s7-dominant-pooled" / "features"
    assert made == [(features, SCALE_BLEND)]
    (cmd,) = calls
    assert cmd[:2] == ["train-field", str(data)]
    assert cmd[cmd.index("--features") + 1] == str(features)
    assert cmd[cmd.index("--package") + 1] == str(pkg)
    assert cmd[cmd.index("--field-steps") + 1] == "1500"
    assert not any(f in cmd for f in ("--lam", "--no-dotsim", "--balance"))
    clip_build(tmp_path, 7, data, "dominant pooled", 1500, STANDIN, STANDIN_DINO, 1)  # recorded
    assert len(calls) == 1 and len(made) == 1
