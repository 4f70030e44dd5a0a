"""Regenerate the inspector's screenshots in docs/images (viewer-*.png) from the bundled demo scene.

    python scripts/make_viewer_pictures.py

Serves models/ on a free port, drives ``fmgs-client view`` under xvfb-run as tests/client/test_viewer.py
does (tests/helpers/drive_viewer.py: "red cube", each picture mode, an instance, segmentation) and copies
the window captures.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PICTURES = {
    "2-query-composite": "viewer-query.png",
    "2-query-relevancy": "viewer-relevancy.png",
    "2-query-rgb": "viewer-rgb.png",
    "3-instance": "viewer-instance.png",
    "4-segment": "viewer-segment.png",
}


def main() -> int:
    from fmgs_server.config import ServerConfig
    from fmgs_server.server import start_server

    xvfb = shutil.which("xvfb-run")
    if xvfb is None:
        raise SystemExit("needs xvfb-run (Debian: xvfb xauth)")
    srv = start_server(ServerConfig(models=ROOT / "models", port=0))
    with tempfile.TemporaryDirectory() as tmp:
        try:
            cmd = [
                xvfb,
                "-a",
                "-s",
                "-screen 0 1280x800x24",
                sys.executable,
                "-m",
                "tests.helpers.drive_viewer",
            ]
            cmd += [srv.address, "demo", tmp, "--shots"]
            subprocess.run(cmd, cwd=ROOT, check=True, timeout=600)
        finally:
            srv.stop(0)
        from PIL import Image

        for src, dst in PICTURES.items():
            # 256 colours keep a window capture a fifth of its size and look the same.
            Image.open(Path(tmp) / f"{src}.png").convert("RGB").quantize(256).save(
                ROOT / "docs" / "images" / dst, optimize=True
            )
            print(f"wrote docs/images/{dst}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
