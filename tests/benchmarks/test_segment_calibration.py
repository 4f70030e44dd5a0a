"""benchmarks.segment_calibration: the raw rule is the served segmentation, the scene max is each class's
best Gaussian, and a stretched absent name takes pixels."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.segment_calibration import RULES, calibrated_labels, divisors, report
from tests.benchmarks.test_lerf_lift import NameEncoder, scene  # noqa: F401 (the fixture)

ROOT = Path(__file__).resolve().parents[2]


def _labels(engine, ds, classes: torch.Tensor, divisor: torch.Tensor) -> list[np.ndarray]:
    from fmgs.query.segment import class_dots

    out = []
    for fr in ds.frames:
        dots, alpha = class_dots(engine, classes, fr.camera)
        out.append(calibrated_labels(dots, alpha, divisor))
    return out


def test_raw_rule_is_the_served_segmentation(scene):  # noqa: F811
    from fmgs.query.engine import SceneEngine
    from fmgs.query.segment import segment

    _, ds, pkgs, table = scene
    e = SceneEngine.open(pkgs[0])
    classes = table[1:]
    d = divisors(e, classes, torch.ones(len(classes), dtype=torch.bool))
    assert torch.equal(d["raw"], torch.ones(len(classes)))
    for fr, got in zip(ds.frames, _labels(e, ds, classes, d["raw"]), strict=True):
        want = segment(e, classes, fr.camera, per_gaussian=False).pixel_labels.numpy()
        assert np.array_equal(got, want)


def test_scene_max_is_each_class_best_gaussian(scene):  # noqa: F811
    from fmgs.query.engine import SceneEngine
    from fmgs.scene.package import load_scene

    _, _, pkgs, table = scene
    e = SceneEngine.open(pkgs[0])
    classes = table[1:]
    found = torch.tensor([True, False] * len(classes))[: len(classes)]
    d = divisors(e, classes, found)
    best = (load_scene(pkgs[0]).embeddings.double() @ classes.double().T).amax(0)
    assert bool((best > 0).all())  # embeddings lie near their names: no class is left raw here
    torch.testing.assert_close(d["scene max"].double(), best, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(
        d["scene max if present"], torch.where(found, d["scene max"], torch.ones(len(found)))
    )


class _Dots:
    """An engine whose every Gaussian's class dots are given."""

    def __init__(self, dots: torch.Tensor) -> None:
        self.dots = dots

    def channels(self, vectors: torch.Tensor, rows=None) -> torch.Tensor:
        return self.dots


def test_a_class_no_gaussian_points_to_stays_raw():
    dots = torch.tensor([[-0.5, 0.4, 0.0], [-0.2, 0.8, 0.0]])
    d = divisors(_Dots(dots), torch.zeros(3, 4), torch.ones(3, dtype=torch.bool))
    assert d["scene max"].tolist() == [1.0, pytest.approx(0.8), 1.0]
    labels = calibrated_labels(torch.tensor([[[-0.2, -0.1, -0.3]]]), torch.ones(1, 1), d["scene max"])
    assert labels.tolist() == [[1]]  # dividing by a negative max would have made -0.2 the best


def test_a_stretched_absent_name_takes_pixels(scene):  # noqa: F811
    from fmgs.query.engine import SceneEngine

    _, ds, pkgs, table = scene
    e = SceneEngine.open(pkgs[0])
    absent = NameEncoder().encode_text(["a thing not in the scene"])
    classes = torch.cat([table[1:], absent])
    n = len(classes)
    d = divisors(e, classes, torch.ones(n, dtype=torch.bool))
    taken = {
        r: sum(int(np.sum(lab == n - 1)) for lab in _labels(e, ds, classes, d[r]))
        for r in ("raw", "scene max")
    }
    assert taken["scene max"] > taken["raw"], taken  # why the rule presumes every class is present


def test_report_renders_every_rule():
    row = {
        "seed": 201,
        "absent": ["red cone"],
        "kinds": {
            k: {
                w: {"miou": dict(zip(RULES, (0.7, 0.72, 0.71), strict=True)), "found": 3, "texts": 4}
                for w in ("scene names", "with absent names")
            }
            for k in ("labels", "dominant")
        },
    }
    d = {"rows": [row], "machine": {"date": "2026-12-01", "cpu": "c", "cores": 2, "gpu": None, "commit": "x"},
         "command": "python -m benchmarks.segment_calibration --out O", "notes": ["a note"]}  # fmt: skip
    text = report(d)
    assert "| dominant | with absent names | 0.700 | 0.720 | 0.710 |" in text
    assert "| 201 | labels | scene names | 0.700 | 0.720 | 0.710 | 3/4 |" in text and "- a note" in text


def test_docs_quote_the_calibration():
    """docs/field.md's figures for per-class calibration are SEGMENT_CALIBRATION's means."""
    d = json.loads((ROOT / "benchmarks" / "results" / "SEGMENT_CALIBRATION.json").read_text())
    docs = (ROOT / "docs" / "field.md").read_text()
    for kind in ("labels", "dominant"):
        for which in ("scene names", "with absent names"):
            for rule in RULES:
                m = float(np.mean([r["kinds"][kind][which]["miou"][rule] for r in d["rows"]]))
                assert f"{m:.3f}" in docs, (kind, which, rule, m)
