"""The inspector window, driven as a user would under Xvfb with Mesa's software renderer (llvmpipe), on the
bundled demo scene served by the real server. tests/helpers/drive_viewer.py runs the window in its own
process (Open3D's application starts once per process) and records what it drew; this test compares that
with the server's own answers."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

ROOT = Path(__file__).resolve().parents[2]
XVFB = shutil.which("xvfb-run")
if XVFB is None and os.environ.get("CI"):
    raise RuntimeError("xvfb-run is missing: .ci/install installs it (requirements/apt.txt: xvfb, xauth)")
pytestmark = [
    pytest.mark.skipif(XVFB is None, reason="needs xvfb-run (Debian: xvfb xauth)"),
    pytest.mark.slow,  # a window under Xvfb driven against a real server
]


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """The driver serves models/ itself (so it can stop and restart the server) on a free port."""
    out = tmp_path_factory.mktemp("viewer")
    cmd = [XVFB, "-a", "-s", "-screen 0 1280x800x24", sys.executable, "-m", "tests.helpers.drive_viewer"]
    p = subprocess.run(
        [*cmd, f"serve:{ROOT / 'models'}", "demo", str(out), "--shots"],
        cwd=ROOT, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return out, json.loads((out / "viewer.json").read_text())


def test_points_drawn_are_the_scenes(drive):
    _, rec = drive
    s = rec["scene"]
    assert s["drawn"] == s["geometry"] > 1000 and s["drawn_equals_geometry"]
    assert np.allclose(s["drawn_bounds"], s["geometry_bounds"])
    assert "demo (ready)" in s["status"]


def test_query_recolours_by_relevancy_and_draws_the_instance_boxes(drive):
    _, rec = drive
    q = rec["query"]
    assert q["index_equal"] and q["relevancy_equal"] and q["points_equal_means"]
    assert q["top_is_high_end"], (q["top_colour"], q["map_high_end"])
    assert q["dimmed_scene"]
    assert q["instances"] >= 1 and q["box_points"] == 8 * q["instances"] and q["boxes_equal_instances"]
    assert q["presence_line"].startswith("red cube: found")
    i = rec["instance"]
    assert i["rows"] == q["instances"] and i["moved"] and i["looks_at_instance"]


def test_picture_panel_is_the_servers_render_of_the_view(drive):
    _, rec = drive
    p = rec["picture"]
    assert p["shown_has_relevancy"], "the panel shows a colour-only picture: the old feed's"
    assert p["relevancy_equal"] and p["rgb_equal"] and p["alpha_equal"]
    assert max(p["size"]) == 320
    assert len(set(rec["modes"].values())) == 3  # composite, relevancy and colour differ


def test_exports_segmentation_and_errors(drive):
    _, rec = drive
    cam = json.loads(Path(rec["exports"]["camera"]).read_text())
    assert len(cam["viewmat"]) == 4 and cam["width"] > 0
    assert any(n.endswith("_boxes.ply") for n in rec["exports"]["ply"])
    assert rec["segment"]["labelled"] > 0 and rec["segment"]["classes"][0] == "floor"
    assert "NOT_FOUND" in rec["error"]["status"] and "Traceback" not in rec["error"]["status"]
    assert rec["error"]["recovered"]


def test_window_survives_the_server_going_away(drive):
    _, rec = drive
    r = rec["restart"]
    assert "UNAVAILABLE" in r["status_down"] and "Traceback" not in r["status_down"]
    assert r["error_up"] == "" and r["picture_after"]


def test_screenshots_are_not_blank(drive):
    out, _ = drive
    for name in ["1-scene", "2-query-composite", "4-segment", "view"]:
        img = np.asarray(Image.open(out / f"{name}.png").convert("RGB"))
        view = img[:, : img.shape[1] * 2 // 3]  # the 3D view's part of the window
        assert view.std() > 5.0, name
        assert len(np.unique(view.reshape(-1, 3), axis=0)) > 50, name
