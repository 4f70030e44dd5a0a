"""The inspector window on edge cases, under Xvfb against the in-process fake service: a scene with no
Gaussians drawn, answers with zero rows, phrases that are only separators, a server sending NaN, and
exports into a folder that cannot be written. tests/helpers/drive_viewer_edges.py drives the window in its
own process and records what it showed."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
XVFB = shutil.which("xvfb-run")
if XVFB is None and os.environ.get("CI"):
    raise RuntimeError("xvfb-run is missing: .ci/install installs it (requirements/apt.txt: xvfb, xauth)")
pytestmark = pytest.mark.skipif(XVFB is None, reason="needs xvfb-run (Debian: xvfb xauth)")


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    pytest.importorskip("open3d")
    out = tmp_path_factory.mktemp("viewer-edges")
    driver = [sys.executable, "-m", "tests.helpers.drive_viewer_edges", str(out)]
    cmd = [XVFB, "-a", "-s", "-screen 0 1024x768x24", *driver]
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return json.loads((out / "edges.json").read_text())


def test_scene_without_gaussians_and_empty_answers(rec):
    assert rec["scene"]["drawn"] == 0 and rec["scene"]["error"] == ""
    assert rec["scene"]["picture"][2] == 3  # the picture panel still shows the server's render
    assert "type phrases separated by ';'" in rec["separators_only"]["status"]
    e = rec["empty_answers"]
    assert e["rows"] == [0, 0] and e["error"] == "" and "nan" not in e["legend"]


def test_exports_into_an_unwritable_folder_are_a_status_line(rec):
    for name, what in [("ply", "Answer PLY"), ("camera", "Camera JSON"), ("screenshot", "Screenshot")]:
        s = rec[f"export_{name}"]
        assert s.get("raised") is None, s["raised"]  # nothing escapes the button's callback
        assert s["error"].startswith(f"{what}: ") and "not-a-folder" in s["error"], s
        assert s["error"] in s["status"] and "wrote" not in s["status"]


def test_a_server_sending_nan_is_refused_by_name(rec):
    n = rec["nan_answer"]
    assert "DATA_LOSS" in n["error"] and "text[0].relevancy: 3 of 3 values are NaN or infinite" in n["error"]
    assert n["answers"] == 2 and "nan" not in n["legend"]  # the previous answers stay drawn
