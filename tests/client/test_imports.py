"""The thin client package (``fmgs_client``): it imports without torch and loads nothing heavy, and it
exports its public API."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import fmgs_client
from fmgs_client import client, retry, types

ROOT = Path(__file__).resolve().parents[2]


def test_client_imports_without_torch():
    code = (
        "import sys; sys.modules['torch'] = None\n"
        "import fmgs_client, fmgs_client.client, fmgs_client.cli, fmgs_client.types\n"
        "import fmgs_client.open3d_tools, fmgs_wire.images, fmgs_client.ply\n"
        "bad = [m for m in ('fmgs', 'torch', 'open3d', 'PIL', 'plyfile', 'rich') if sys.modules.get(m)]\n"
        "assert not bad, bad\n"
        "print('ok')\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr


def test_package_exports_the_public_api():
    public = "Box CameraSpec FmgsClient FmgsError Geometry Instance Pixel PointResult Presence RenderResult "
    public += "RetryPolicy SceneInfo SegmentResult TextAnswer"
    assert sorted(fmgs_client.__all__) == public.split()
    for name in fmgs_client.__all__:
        home = client if name.startswith("Fmgs") else retry if name == "RetryPolicy" else types
        assert getattr(fmgs_client, name) is getattr(home, name)
    project = (ROOT / "pyproject.toml").read_text()
    assert f'version = "{fmgs_client.__version__}"' in project
