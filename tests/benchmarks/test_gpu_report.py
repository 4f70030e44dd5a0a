"""The GPU report writer: every section renders from partial, failed or complete figures."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.gpu_report import NOT_RUN, write_report

ROOT = Path(__file__).resolve().parents[2]


def test_report_from_nothing_says_not_run(tmp_path):
    write_report({}, tmp_path / "GPU.md")
    text = (tmp_path / "GPU.md").read_text()
    assert text.count("not run") >= 6 and NOT_RUN in text


def test_report_names_failed_and_skipped_parts(tmp_path):
    res = {"parts": {"pose": {"error": "RuntimeError: boom"}, "paper": {"skipped": "no time left"}}}
    write_report(res, tmp_path / "GPU.md")
    text = (tmp_path / "GPU.md").read_text()
    assert "failed: RuntimeError: boom" in text and "skipped: no time left" in text


def test_committed_report_is_written_from_the_committed_figures(tmp_path):
    figures = json.loads((ROOT / "benchmarks" / "results" / "GPU.json").read_text())
    write_report(figures, tmp_path / "GPU.md")
    assert (tmp_path / "GPU.md").read_text() == (ROOT / "benchmarks" / "results" / "GPU.md").read_text()
    tests = figures["parts"]["tests"]
    assert tests["passed"] > 0 and tests["collected"] == tests["passed"] + len(tests["failures"])
    # A CUDA test that failed in the committed run is listed in the report and explained in its notes.
    notes = " ".join(figures.get("notes", []))
    for failure in tests["failures"]:
        name = failure.split("::")[-1].split(":")[0]
        assert name in notes, f"{failure} is not explained in GPU.json's notes"


def test_readme_quotes_the_committed_gpu_figures():
    parts = json.loads((ROOT / "benchmarks" / "results" / "GPU.json").read_text())["parts"]
    readme = " ".join((ROOT / "README.md").read_text().split())
    quoted = (
        f"relevancy images at {parts['pose']['engine_cuda_cached_images_per_s']:.1f}/s",
        f"text query in {parts['text10m']['cuda_ms_median']:.2f} ms",
        f"render at {parts['paper']['480x270_stored_one_call_fps']:.1f} FPS (480x270)",
        f"the paper's {parts['paper']['paper_fps']}",
    )
    for q in quoted:
        assert q in readme, q
