"""A CI-sized scene seen from a grazing ring with its sky undeclared, built at the defaults with trained
geometry (reduced steps): every held-out view keeps its geometry and its queries (benchmarks/unseen.py
--rig grazing --undeclared-background holds the full-size report, benchmarks/results/FIELD_GRAZING.md)."""

from __future__ import annotations

import json
import logging

import pytest

from fmgs.cli import main

pytestmark = pytest.mark.slow  # 3DGS and field training through `fmgs build`: minutes

GS_STEPS = 600
# 300 field steps (2026-11-29): held-out views' 2D 4/5, 5/5 and 5/6, mIoU 0.626; 600 cost twice the time
# for what the floors below ask.
FIELD_STEPS = 300
# At these reduced steps a grazing held-out view lands near the build's 20 dB threshold (19.4 dB measured
# 2026-11-27): it may fall below, and then the build must name it; none may fall far below.
VIEW_PSNR_FLOOR = 18.0
VIEW_2D_FLOOR = 0.5  # of the queries in any one held-out view
MIOU_FLOOR = 0.5


@pytest.fixture(scope="module")
def grazing(tmp_path_factory):
    from fmgs.synth import SynthConfig, generate

    tmp = tmp_path_factory.mktemp("grazing")
    data = tmp / "scene"
    cfg = SynthConfig(
        views=24, width=64, height=48, objects=6, seed=11, points=6000, preset="cluttered", rig="grazing",
        declare_background=False,
    )  # fmt: skip
    generate(data, cfg)
    warnings: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda record: warnings.append(record.getMessage())
    logging.getLogger("fmgs.build.pipeline").addHandler(handler)
    args = ["build", str(data), "--name", "g", "--models", str(tmp / "models"), "--targets", "labels"]
    args += ["--gs-steps", str(GS_STEPS), "--grad-threshold", "0.001", "--field-steps", str(FIELD_STEPS)]
    try:
        assert main([*args, "--device", "cpu"]) == 0
    finally:
        logging.getLogger("fmgs.build.pipeline").removeHandler(handler)
    return tmp, data, warnings


def test_every_held_out_view_keeps_its_geometry_and_its_queries(grazing):
    from benchmarks.unseen import views_section
    from fmgs.data.dataset import load_dataset
    from fmgs.features.text import MiniLMTextEncoder
    from fmgs.query.engine import SceneEngine
    from fmgs.synth import BACKGROUND
    from fmgs.train.evaluate_field import evaluate_field

    tmp, data, warnings = grazing
    work = tmp / "models" / ".work" / "g"
    train = json.loads((work / "gs" / "train.json").read_text())
    assert train["background_source"] == "learned"
    assert max(abs(a - b) for a, b in zip(train["background"], BACKGROUND, strict=True)) < 0.03
    geometry = json.loads((work / "geometry.json").read_text())
    views = {v["name"]: v["psnr"] for v in geometry["per_view"]}
    assert min(views.values()) >= VIEW_PSNR_FLOOR, views
    assert geometry["below"] == sorted((n for n in views if views[n] < 20.0), key=views.get)
    for name in geometry["below"]:  # a view below the threshold is named on the terminal with its figure
        assert any(name in w and f"({views[name]:.1f} dB)" in w for w in warnings), (name, warnings)
    assert geometry["floaters"]["cameras_checked"] > 0

    engine = SceneEngine.open(tmp / "models" / "g")
    ds = load_dataset(data)
    test = ds.split(8)[1]
    q = evaluate_field(engine, ds, MiniLMTextEncoder(), test, data / "scene.json")
    assert set(q.per_view_2d) == {ds.frames[i].name for i in test}
    assert sum(n for _, n in q.per_view_2d.values()) == q.queries_2d
    low_ring = [ds.frames[i].name for i in test if i % 3 == 2]
    assert low_ring, "the held-out views include the grazing ring"
    seen = f"{q.per_view_2d}, mIoU {q.miou:.3f} {q.per_class_iou}, {q.failures}"
    for hit, n in q.per_view_2d.values():
        assert n == 0 or hit / n >= VIEW_2D_FLOOR, seen
    assert q.localisation_2d >= 0.8 and q.miou >= MIOU_FLOOR, seen

    scene = {
        "seed": 11, "per_view_2d": q.per_view_2d, "geometry": geometry,
    }  # fmt: skip
    text = "\n".join(views_section([scene]))
    for name, (hit, n) in q.per_view_2d.items():
        assert f"| 11 | {name} | {views[name]:.2f} | {hit}/{n} |" in text
    assert f"below 20 dB: {', '.join(geometry['below']) or 'none'}" in text
