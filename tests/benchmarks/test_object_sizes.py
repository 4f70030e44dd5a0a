"""benchmarks.object_sizes: the size bands, the areas they are judged on, the means per band, and the
committed report written from its committed figures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks.object_sizes import BAND_NAMES, band, band_means, label_areas, report, served_ious

RESULTS = Path(__file__).resolve().parents[2] / "benchmarks" / "results"


def test_bands_split_at_a_quarter_percent_and_one_percent():
    assert [band(s) for s in (0.0, 0.0024, 0.0025, 0.0099, 0.01, 1.0)] == [0, 0, 1, 1, 2, 2]
    assert len(BAND_NAMES) == 3
    for bad in (-0.001, 1.5, float("nan")):
        with pytest.raises(ValueError, match="share of the image"):
            band(bad)


def test_label_areas_are_mean_pixels_per_view():
    a = np.array([[0, 1], [2, 2]])
    b = np.array([[2, 2], [2, 2]])
    assert label_areas([a, b], 4).tolist() == [0.5, 0.5, 3.0, 0.0]


def test_band_means_leave_out_unscored_objects():
    objs = [
        {"share_served": 0.001, "served": {"x": 0.2}},
        {"share_served": 0.002, "served": {"x": 0.4}},
        {"share_served": 0.02, "served": {"x": 0.9}},
        {"share_served": 0.02, "served": {"x": None}},
    ]
    got = band_means(objs, "served", "x")
    assert got[0] == (2, pytest.approx(0.3)) and got[2] == (1, pytest.approx(0.9))
    assert got[1][0] == 0 and np.isnan(got[1][1])


def test_served_ious_keep_the_builds_made_again_apart():
    row = {
        "kinds": {"labels": {"class_iou": {"a": 0.9}}, "dominant": {"class_iou": {"a": 0.5}}},
        "refit_labels": {"class_iou": {"a": 0.8}},
        "refit_variants": {"dominant": {"class_iou": {"a": 0.6}}},
    }
    got = served_ious(row)
    assert got == {
        "labels": {"a": 0.9},
        "dominant": {"a": 0.5},
        "labels (made again)": {"a": 0.8},
        "dominant (made again)": {"a": 0.6},
    }


def test_committed_report_is_written_from_the_committed_figures():
    d = json.loads((RESULTS / "OBJECT_SIZES.json").read_text())
    assert report(d) == (RESULTS / "OBJECT_SIZES.md").read_text()
    # every object of the scores is placed in a band, and the bands hold all of them
    objs = [o for r in d["rows"] for o in r["objects"]]
    assert sum(n for n, _ in band_means(objs, "served", "labels")) == len(objs)
