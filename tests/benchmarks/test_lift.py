"""benchmarks.lift: the targets lifted onto the Gaussians by the renderer's adjoint, against a pixel loop."""

from __future__ import annotations

import pytest
import torch

from benchmarks.lift import lift, lift_reference
from fmgs.features.cache import FeatureCache, FeatureCacheWriter, TargetInfo
from fmgs.synth import SynthConfig, generate
from tests.helpers.scenes import surface_ply


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from fmgs.data.dataset import load_dataset
    from fmgs.io.ply import read_ply

    root = tmp_path_factory.mktemp("lift")
    generate(root / "scene", SynthConfig(views=3, width=24, height=18, objects=2, points=250, seed=3))
    surface_ply(root / "scene", root / "g.ply", scale=0.15)
    ds = load_dataset(root / "scene")
    gen = torch.Generator().manual_seed(0)
    targets = {"clip": TargetInfo("t/clip", 5, True)}
    with FeatureCacheWriter(root / "cache", targets) as w:
        for k, fr in enumerate(ds.frames):
            clip = torch.nn.functional.normalize(torch.randn(9, 12, 5, generator=gen), dim=-1)
            mask = None
            if k == 1:  # half the view unsupervised: its pixels must not count
                mask = torch.zeros(9, 12, dtype=torch.uint8)
                mask[:, :6] = 1
            w.add(fr.name, clip=clip, mask=mask)
    return ds, read_ply(root / "g.ply"), FeatureCache.open(root / "cache")


def test_lift_is_the_weighted_mean_of_the_pixels_each_gaussian_reaches(scene):
    ds, g, cache = scene
    frames = list(range(len(ds.frames)))
    fast, ref = lift(g, ds, cache, frames), lift_reference(g, ds, cache, frames)
    seen = ref.weight > 0
    assert 0 < int(seen.sum()) < g.num  # some Gaussians are reached, some are not
    torch.testing.assert_close(fast.weight, ref.weight, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(fast.embeddings, ref.embeddings, rtol=1e-5, atol=1e-6)
    assert torch.all(fast.embeddings[~seen] == 0)
    norms = fast.embeddings[seen].norm(dim=1)
    torch.testing.assert_close(norms, torch.ones_like(norms))
    assert torch.isfinite(fast.embeddings).all()


def test_lift_needs_frames(scene):
    ds, g, cache = scene
    with pytest.raises(ValueError, match="no frames"):
        lift(g, ds, cache, [])
