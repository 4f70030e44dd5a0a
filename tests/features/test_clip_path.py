"""The CLIP-target path on meaning, CI-sized (benchmarks/clip_path.py is the full report): on a small scene
of the wider generated world, with two objects whose colour-shape pair no stand-in saw, the CLIP stand-in
(benchmarks/standin) embeds every crop of the hybrid pyramid and the DINO stand-in (benchmarks/standin_dino)
gives the dense map the scales are blended by and the DINO head learns. The target maps must put object
pixels at their own names, and a scene built from them must place names where their objects are, close to
the same scene built from label targets."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.clip_path import STANDIN, STANDIN_DINO
from fmgs.features.sizes import SCALE_BLEND, SCALE_BLENDS
from fmgs.synth import SynthConfig, generate
from tests.helpers.scenes import surface_ply

pytestmark = pytest.mark.slow

SEED = 7
"""No stand-in training (9001-9160), held-out (9901-9904) or benchmark (201-203) seed."""
VIEWS = 16
# Floors, about 0.8 of what the scene gave with the stand-ins as shipped (the 300-scene CLIP stand-in) and
# 16 views (2026-11-29; with 24 views, before: object pixels 0.631, novel 0.647, mIoU 0.256, 2D 0.533,
# share 0.48, 18 of 19 absent rejected; labels mIoU 0.530, 2D 0.800). 16 views keep CI shorter.
TARGET_OBJECT_PIXELS = 0.5  # 0.628 with the default blend (the paper's mean: 0.526)
TARGET_NOVEL_PIXELS = 0.5  # 0.635 on the two held-out-name objects
CLIP_MIOU = 0.22  # 0.289 (labels: 0.556)
CLIP_2D = 0.46  # 0.545 (labels: 0.727)
MIOU_SHARE = 0.42  # 0.52 of the label path's mIoU
ABSENT_REJECTED = 0.85  # 18 of 19 absent objects and unrelated things on a Xeon, 17 of 19 on an AMD EPYC
# (the same commit: the CPU's float kernels move one query; labels: 19 of 19 on both)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    data = tmp_path_factory.mktemp("clip_path") / "scene"
    cfg = SynthConfig(views=VIEWS, width=96, height=72, objects=6, novel=2, seed=SEED, points=8000,
                      preset="world")  # fmt: skip
    generate(data, cfg)
    return data


def test_the_default_blend_puts_object_pixels_at_their_names(scene):
    """Before distillation, on four views: the default blend of the scales against the paper's equal mean
    (see the module's floors for the figures when written)."""
    from benchmarks.clip_targets import rates, target_candidates

    took: dict[str, float] = {}
    r = rates([target_candidates(scene, STANDIN, STANDIN_DINO, views=4, seconds=took, regions=False)])
    # the work-precision report's times: per part, the pooled blend's including its blend's
    assert took["views"] == 4 and took["pyramid"] > 0 and took["dino"] > 0, took
    assert all(took[f"{b} + pooled"] >= took[b] >= 0 for b in SCALE_BLENDS), took
    assert r[SCALE_BLEND]["object_pixels"] >= TARGET_OBJECT_PIXELS, r[SCALE_BLEND]
    assert r[SCALE_BLEND]["novel_object_pixels"] >= TARGET_NOVEL_PIXELS, r[SCALE_BLEND]
    assert r[SCALE_BLEND]["object_pixels"] >= r["mean"]["object_pixels"], (r[SCALE_BLEND], r["mean"])


def test_clip_targets_place_names_close_to_label_targets(scene):
    """Both builds on one surface-sampled 3DGS at the build's defaults but 300 field steps (CLIP: the
    stand-ins, the default blend, DINO head and dotsim); scored on held-out views as served."""
    from benchmarks.unseen import presence_rates, score_presence
    from fmgs.cli import main
    from fmgs.data.dataset import load_dataset
    from fmgs.features.text import MiniLMTextEncoder
    from fmgs.query.engine import SceneEngine
    from fmgs.train.evaluate_field import evaluate_field

    work = scene.parent
    surface_ply(scene, work / "surface.ply", scale=0.03)
    clip = ["--clip-model", f"standin:{STANDIN}", "--dino-model", f"standin-dino:{STANDIN_DINO}"]
    kinds = {"clip": clip, "labels": []}
    for kind, extra in kinds.items():
        args = ["build", str(scene), "--name", kind, "--models", str(work / "models"), "--targets", kind]
        args += [*extra, "--ply", str(work / "surface.ply"), "--field-steps", "300", "--device", "cpu"]
        assert main(args) == 0
    ds = load_dataset(scene)
    enc = MiniLMTextEncoder()
    names = json.loads((scene / "scene.json").read_text())["label_names"]
    q, absent = {}, {}
    for kind in kinds:
        engine = SceneEngine.open(work / "models" / kind)
        assert engine.manifest.extra["targets"]["kind"] == kind
        if kind == "clip":
            assert engine.manifest.extra["targets"]["scale_blend"] == SCALE_BLEND
        q[kind] = evaluate_field(engine, ds, enc, ds.split(8)[1], scene / "scene.json")
        hits, asked = (sum(v[i] for v in q[kind].per_object_2d.values()) for i in (0, 1))
        assert hits / asked == pytest.approx(q[kind].localisation_2d)  # the per-object split adds up
        assert len(q[kind].per_object_3d) == len(names) - 2
        rates = presence_rates(score_presence(engine, enc, names))
        rejected, asked = (sum(rates[k][i] for k in ("absent object", "unrelated")) for i in (0, 1))
        absent[kind] = rejected / asked
    assert q["clip"].miou >= CLIP_MIOU, q["clip"]
    assert q["clip"].localisation_2d >= CLIP_2D, q["clip"]
    assert q["clip"].miou >= MIOU_SHARE * q["labels"].miou, (q["clip"].miou, q["labels"].miou)
    assert absent["clip"] >= ABSENT_REJECTED and absent["labels"] >= ABSENT_REJECTED, absent
