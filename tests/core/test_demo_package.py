"""The committed demo scene (``models/demo``, made by ``scripts/make_demo.py``) loads, stays small and
answers its object names with Gaussians inside those objects' boxes."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from fmgs.features.models import MINILM_ID

DEMO = Path(__file__).resolve().parents[2] / "models" / "demo"
MAX_BYTES = 10 * 2**20


@pytest.fixture(scope="module")
def demo():
    from fmgs.features.text import load_text_encoder
    from fmgs.scene.package import load_scene

    scene = load_scene(DEMO)
    return scene, load_text_encoder(scene.encoder_id)


def test_demo_is_a_small_minilm_scene(demo):
    scene, _ = demo
    assert scene.name == "demo" and scene.encoder_id == MINILM_ID and scene.dim == 384
    assert scene.field is not None and scene.manifest.field.dtype == "float16"
    assert sum(f.stat().st_size for f in DEMO.rglob("*") if f.is_file()) < MAX_BYTES
    assert sorted(f.name for f in DEMO.iterdir()) == [
        "embeddings.safetensors",
        "field.safetensors",
        "gaussians.safetensors",
        "manifest.json",
        "query_state.safetensors",
    ]


def test_each_object_name_ranks_a_gaussian_in_its_box_first(demo):
    from fmgs.query.engine import SceneEngine

    scene, enc = demo
    engine = SceneEngine.open(DEMO)  # as the server opens it
    extra = scene.manifest.extra
    objects = [o for o in extra["objects"] if o["label"] >= 2]  # label 1 is the floor
    assert len(objects) == 6 and all(o["name"] in extra["label_names"] for o in objects)
    q = enc.encode_text([o["name"] for o in objects])
    tops = []
    for o, e in zip(objects, q, strict=True):
        top = int(engine.text_query(e, top_k=1).index[0])
        tops.append(top)
        p = scene.gaussians.means[top].double()
        lo, hi = torch.tensor(o["aabb_min"]).double(), torch.tensor(o["aabb_max"]).double()
        outside = float(((lo - p).clamp_min(0) + (p - hi).clamp_min(0)).norm())
        margin = float(scene.gaussians.scales[top].max())  # surface Gaussians straddle flat faces
        assert outside <= margin, f"{o['name']!r}: top Gaussian {outside:.3f} outside its box"
    assert len(set(tops)) == len(tops)


def test_float16_field_reproduces_the_stored_embeddings(demo):
    scene, _ = demo
    from fmgs.field.neighbours import neighbour_mean, reach_of, stored_neighbours

    g = scene.gaussians.subset(scene.selected)
    means = g.means
    with torch.no_grad():
        f = scene.field(means, dino=False).clip
    # Stored embeddings are the field averaged over dense neighbourhoods (K from the manifest).
    f = neighbour_mean(means, reach_of(g.scales), f, stored_neighbours(scene.manifest.extra))
    cos = (f * scene.embeddings).sum(1) / scene.embeddings.norm(dim=1)
    assert float(cos.min()) > 0.99
