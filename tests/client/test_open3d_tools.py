"""The client's Open3D helpers (``fmgs_client.open3d_tools``): geometry export and screenshots, with the
numpy fallback where Open3D cannot render."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fmgs_client.ply import read_ply
from fmgs_client.types import TextAnswer
from fmgs_wire.images import colorize, decode_png
from tests.helpers.client_fakes import answer_with_instances

ROOT = Path(__file__).resolve().parents[2]


def test_open3d_export(tmp_path):
    o3d = pytest.importorskip("open3d")
    from fmgs_client import open3d_tools as ot

    ans = answer_with_instances()
    geoms = ot.answer_geometries(ans)
    assert len(geoms) == 1 + 2 * len(ans.instances)
    paths = ot.export_answer(ans, tmp_path / "ans.ply")
    assert [p.name for p in paths] == ["ans.ply", "ans_boxes.ply"]
    pc = o3d.io.read_point_cloud(str(paths[0]))
    np.testing.assert_allclose(np.asarray(pc.points), ans.mean, atol=1e-6)
    np.testing.assert_allclose(np.asarray(pc.colors), colorize(ans.relevancy) / 255, atol=1e-6)
    ours = read_ply(paths[0])
    np.testing.assert_array_equal(ours.scalars["relevancy"], ans.relevancy)
    ls = o3d.io.read_line_set(str(paths[1]))
    assert len(ls.lines) == 12 * 2 * len(ans.instances) and len(ls.points) == 8 * 2 * len(ans.instances)
    np.testing.assert_allclose(np.asarray(ls.points)[:8].mean(0), ans.instances[0].aabb.center, atol=1e-9)
    with pytest.raises(ValueError, match="fields=\\['mean'\\]"):
        ot.export_answer(TextAnswer("x", np.zeros(0, np.int64), np.zeros(0, np.float32)), tmp_path / "n.ply")


def test_numpy_screenshot_fallback(tmp_path):
    from fmgs_client import open3d_tools as ot

    ans = answer_with_instances()
    path = ot.screenshot(ans, tmp_path / "s.png", 160, 120, method="numpy")
    img = decode_png(path.read_bytes())
    assert img.shape == (120, 160, 3)
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 20  # points in many colours, boxes, background
    # The first instance's centroid lands where the camera projects it.
    cam = ot.view_camera(ans, 160, 120)
    uv, _ = cam.project(ans.instances[0].centroid[None])
    x, y = np.floor(uv[0]).astype(int)
    assert (img[y - 3 : y + 4, x - 3 : x + 4] != 255).any()


_SHOT = """
from tests.helpers.client_fakes import answer_with_instances
from fmgs_client import open3d_tools as ot
ot.screenshot(answer_with_instances(), {out!r}, 160, 120, method="open3d")
"""


def test_open3d_headless_screenshot(tmp_path):
    pytest.importorskip("open3d")
    import ctypes.util

    if ctypes.util.find_library("vulkan") is None:
        pytest.skip("no libvulkan (Debian libvulkan1 mesa-vulkan-drivers): Open3D cannot render headless")
    out = tmp_path / "shot.png"
    # A subprocess: Filament aborts the whole process when it finds no usable device.
    code = _SHOT.format(out=str(out))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}  # the child imports tests.helpers from the checkout
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    img = decode_png(out.read_bytes())
    assert img.shape == (120, 160, 3)
    colours = np.unique(img.reshape(-1, 3), axis=0)
    assert len(colours) > 20 and (img == 255).all(-1).mean() > 0.5  # white background, coloured points
    # Open3D and the numpy fallback use the same camera: the painted pixels overlap.
    ot = pytest.importorskip("fmgs_client.open3d_tools")
    soft = decode_png(
        ot.screenshot(answer_with_instances(), tmp_path / "n.png", 160, 120, method="numpy").read_bytes()
    )
    a, b = (img != 255).any(-1), (soft != 255).any(-1)
    assert (a & b).sum() / (a | b).sum() > 0.3
