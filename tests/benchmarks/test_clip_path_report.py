"""The committed CLIP-path report (benchmarks/results/CLIP_PATH.md) is written from its committed figures
(CLIP_PATH.json) by the report writer, and the figures docs/field.md and docs/limits.md quote are those
figures."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.clip_path import report, summary

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "results"


def _figures() -> dict:
    return json.loads((RESULTS / "CLIP_PATH.json").read_text())


def test_committed_report_is_written_from_the_committed_figures():
    assert report(_figures()) == (RESULTS / "CLIP_PATH.md").read_text()


def test_docs_quote_the_reports_figures():
    d = _figures()
    docs = (ROOT / "docs" / "field.md").read_text() + (ROOT / "docs" / "limits.md").read_text()
    for kind in ("labels", "paper", "dominant"):
        s = summary(d["rows"], kind)
        for key in ("miou", "localisation_2d", "localisation_3d"):
            assert f"{s[key]:.3f}" in docs, (kind, key, s[key])


def test_committed_target_report_is_written_from_its_figures_and_backs_the_default():
    """CLIP_TARGETS.md (the dev scenes the default blend was chosen on) renders from CLIP_TARGETS.json, and
    the default blend is the best there on object pixels among the blends the build offers."""
    from benchmarks.clip_targets import report as targets_report
    from fmgs.features.sizes import SCALE_BLEND, SCALE_BLENDS

    d = json.loads((RESULTS / "CLIP_TARGETS.json").read_text())
    assert targets_report(d) == (RESULTS / "CLIP_TARGETS.md").read_text()
    best = max(SCALE_BLENDS, key=lambda b: d["rates"][b]["object_pixels"])
    assert best == SCALE_BLEND
