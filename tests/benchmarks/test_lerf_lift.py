"""benchmarks.lerf_lift: the max over scales scored as a served package is, and one cache per scale."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from benchmarks.lerf_lift import _Views, lerf_quality, scale_caches
from fmgs.synth import SynthConfig, generate
from fmgs.vecmath import safe_normalize
from tests.helpers.scenes import surface_ply

D = 16


class NameEncoder:
    """Each text to a seeded unit vector of its own."""

    id = "test/names"
    dim = D

    def encode_text(self, texts: list[str]) -> torch.Tensor:
        rows = [torch.randn(D, generator=torch.Generator().manual_seed(sum(map(ord, t)))) for t in texts]
        return safe_normalize(torch.stack(rows))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A generated scene, its Gaussians, and two packages of them: embeddings near the name of the object
    each Gaussian is nearest to, with a different noise each."""
    from fmgs.data.dataset import load_dataset
    from fmgs.io.ply import read_ply
    from fmgs.scene.package import export_scene

    root = tmp_path_factory.mktemp("lerf")
    generate(root / "scene", SynthConfig(views=8, width=40, height=30, objects=3, points=800, seed=5))
    surface_ply(root / "scene", root / "g.ply", scale=0.08)
    ds, g = load_dataset(root / "scene"), read_ply(root / "g.ply")
    meta = json.loads((root / "scene" / "scene.json").read_text())
    names = meta["label_names"]
    table = NameEncoder().encode_text(names)
    centres = torch.tensor([[(a + b) / 2 for a, b in zip(o["aabb_min"], o["aabb_max"], strict=True)]
                            for o in meta["objects"]], dtype=torch.float32)  # fmt: skip
    near = torch.cdist(g.means.float(), centres).argmin(1)
    labels = torch.tensor([o["label"] for o in meta["objects"]])[near]
    canon = NameEncoder().encode_text(["object", "things", "stuff", "texture"])
    pkgs = []
    for k in range(2):
        gen = torch.Generator().manual_seed(10 + k)
        emb = safe_normalize(table[labels] + 0.9 * torch.randn(g.num, D, generator=gen))
        pkgs.append(export_scene(root / f"p{k}", g, torch.arange(g.num), emb, NameEncoder.id, canon))
    return root / "scene", ds, pkgs, table


def test_one_package_scores_as_evaluate_field(scene):
    from fmgs.query.engine import SceneEngine
    from fmgs.train.evaluate_field import evaluate_field

    data, ds, pkgs, _ = scene
    e = SceneEngine.open(pkgs[0])
    views = list(range(len(ds.frames)))
    ref = evaluate_field(e, ds, NameEncoder(), views, data / "scene.json")
    got = lerf_quality([e], ds, NameEncoder(), views, data / "scene.json")
    assert 0 < ref.miou < 1 and ref.queries_2d > 0  # neither trivial nor empty
    assert got["miou"] == ref.miou and got["class_iou"] == ref.per_class_iou
    assert got["localisation_2d"] == ref.localisation_2d and got["localisation_3d"] == ref.localisation_3d


def _rendered_embedding(engine, package, camera) -> tuple[torch.Tensor, torch.Tensor]:
    """Render-then-dot's half: the blended stored embedding [H,W,D] and alpha [H,W]."""
    from fmgs.render import rasterize
    from fmgs.scene.package import load_scene

    emb = load_scene(package).embeddings.float()
    out = rasterize(*engine.geometry, emb.to(engine.geometry[0]), camera, backend=engine.cfg.backend)
    return out.image.float(), out.alpha.float()


def test_max_over_packages_is_each_pixels_best_scale(scene):
    from fmgs.query.engine import SceneEngine

    _, ds, pkgs, table = scene
    engines = [SceneEngine.open(p) for p in pkgs]
    views = _Views(engines)
    classes = table[1:]
    disagree = 0
    for fr in ds.frames:
        ref, alpha = None, None
        for e, p in zip(engines, pkgs, strict=True):  # render, then dot: the same numbers by linearity
            img, alpha = _rendered_embedding(e, p, fr.camera)
            dots = img @ classes.T
            ref = dots if ref is None else torch.maximum(ref, dots)
        want = ref.argmax(-1).numpy()
        want[alpha.numpy() < 0.1] = -1
        got = views.labels(classes, fr.camera)
        # Ties between near-equal dots may go either way in float32; nothing else may differ.
        close = np.sort(ref.numpy(), -1)
        tie = (close[..., -1] - close[..., -2]) < 1e-5
        assert np.array_equal(got[~tie], want[~tie])
        single = [_Views([e]).labels(classes, fr.camera) for e in engines]
        disagree += int(np.sum(single[0] != single[1]))
    assert disagree > 0  # the packages differ, so the max has something to choose


def test_the_most_relevant_gaussian_is_taken_over_the_packages(scene):
    from fmgs.query.engine import SceneEngine

    _, _, pkgs, table = scene
    engines = [SceneEngine.open(p) for p in pkgs]
    for q in table[1:]:
        hits = [e.text_query(q, top_k=1) for e in engines]
        best = int(np.argmax([float(h.relevancy[0]) for h in hits]))
        want = engines[best].gaussians.means[int(hits[best].index[0])].double()
        torch.testing.assert_close(_Views(engines).top(q), want)


def test_scale_caches_hold_each_scales_map_alone(tmp_path):
    from benchmarks.clip_variants import STANDIN
    from fmgs.data.dataset import load_dataset
    from fmgs.features.cache import FeatureCache
    from fmgs.features.extract import ExtractConfig, feature_size
    from fmgs.features.pyramid import pyramid_for, scale_maps
    from fmgs.features.standin import load_standin

    data = tmp_path / "scene"
    generate(data, SynthConfig(views=3, width=32, height=24, objects=2, points=300, seed=6))
    ds = load_dataset(data)
    dirs, scales = scale_caches(data, tmp_path / "caches", STANDIN)
    clip = load_standin(f"standin:{STANDIN}")
    cfg = pyramid_for(clip)
    assert scales == [float(s) for s in cfg.scales] and len(dirs) == len(scales) > 1
    fr = ds.frames[1]
    image, _ = ds.image(1)
    with torch.inference_mode():
        sm = scale_maps(clip, image, cfg, feature_size(fr.camera, ExtractConfig().feature_scale))
    for d, m in zip(dirs, sm.maps, strict=True):
        cache = FeatureCache.open(d)
        assert len(cache) == len(ds.frames) and "dino" not in cache.targets
        got = cache.load(fr.name).clip.float()
        torch.testing.assert_close(got, safe_normalize(m), atol=2e-3, rtol=0)
    files = sorted(f for d in dirs for f in d.glob("*.safetensors"))
    stamp = [f.stat().st_mtime_ns for f in files]
    scale_caches(data, tmp_path / "caches", STANDIN)  # complete: no map is made or written again
    assert [f.stat().st_mtime_ns for f in files] == stamp


def test_no_packages_is_an_error():
    with pytest.raises(ValueError, match="no packages"):
        _Views([])


def test_report_gives_the_means_and_each_scene():
    from benchmarks.common import machine
    from benchmarks.lerf_lift import report

    def q(m, d2, d3, b=0.0):
        return {"miou": m, "localisation_2d": d2, "localisation_3d": d3, "language_bytes": b}

    rows = [
        {"seed": s, "scales": [0.05, 0.5], "cpu_seconds": {"scale maps": 10.0, "lift": 5.0},
         "kinds": {"blend": q(0.6 + k, 0.9, 0.8, 900), "max over scales": q(0.5 + k, 0.8, 0.7, 1800),
                   "0.05 alone": q(0.55, 0.85, 0.6), "0.5 alone": q(0.2, 0.4, 0.3)}}
        for k, s in ((0.0, 1), (0.1, 2))
    ]  # fmt: skip
    info = {**machine(), "date": "2026-11-30"}
    text = report({"rows": rows, "machine": info, "command": "c", "notes": ["n1"]})
    assert "| blend | 2 | 0.900 | 0.800 | **0.650** | 900 |" in text
    assert "| max over scales | 2 | 0.800 | 0.700 | **0.550** | 1800 |" in text
    assert (
        "| 0.05 alone | 0.850 | 0.600 | 0.550 |" in text and "| 0.5 alone | 0.400 | 0.300 | 0.200 |" in text
    )
    assert "| 2 | max over scales | 0.800 | 0.700 | 0.600 |" in text
    assert "crop edges 0.05, 0.5 of the image" in text and "- n1" in text
    assert "seed 1: scale maps 10, lift 5; seed 2: scale maps 10, lift 5." in text
    rows[1]["cpu_seconds"] = {"scale maps": 0.2}
    text = report({"rows": rows, "machine": info, "command": "c"})
    assert "seed 2: all made by an earlier run." in text
