"""Regenerate docs/images/demo_query.png: the demo scene's colour render beside its relevancy for a text.

Runs the server in this process on a free loopback port and asks it through the thin client, so the
picture is what ``fmgs-client render`` shows:

    python scripts/make_readme_picture.py [--models models] [--scene demo] [--text "red cube"]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from fmgs_client import CameraSpec, FmgsClient
from fmgs_server.config import ServerConfig
from fmgs_server.server import start_server
from fmgs_wire.images import colorize, to_uint8

ROOT = Path(__file__).resolve().parents[1]

GAP = 6
"""White pixels between the two panels."""
EYE = (3.464, -2.0, 1.6)
TARGET = (0.0, 0.0, 0.25)
"""The demo's camera: a pose on its capture ring (radius 4, the upper of its two heights, looking at the
ring's target), where the demo is sharp (docs/limits.md says where it is not); its six objects in view,
the red cube on the left (scene units, z up)."""


def picture(models: Path, scene: str, text: str, camera: CameraSpec) -> np.ndarray:
    """[H, 2W+GAP, 3] uint8: the scene's RGB render, then its relevancy for ``text`` faded by alpha
    (colours and fading as ``fmgs-client render`` writes them)."""
    srv = start_server(ServerConfig(models=models, port=0, workers=1))
    try:
        with FmgsClient(srv.address) as client:
            r = client.render(scene, camera, text, outputs=("relevancy", "alpha", "rgb"))
    finally:
        srv.stop(1.0)
    rel = colorize(r.relevancy).astype(np.float32) * np.clip(r.alpha, 0, 1)[..., None]
    gap = np.full((r.height, GAP, 3), 255, np.uint8)
    return np.concatenate([to_uint8(r.rgb), gap, np.round(rel).astype(np.uint8)], axis=1)


def save_small_png(path: Path, img: np.ndarray) -> None:
    """Write ``img`` as a 256-colour PNG (error-diffused): about a third of the RGB file's size, so the
    README's picture stays small in the repository."""
    from PIL import Image

    rgb = Image.fromarray(img)
    palette = rgb.quantize(256, method=Image.Quantize.MEDIANCUT, kmeans=3)
    rgb.quantize(palette=palette, dither=Image.Dither.FLOYDSTEINBERG).save(path, optimize=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", type=Path, default=ROOT / "models")
    ap.add_argument("--scene", default="demo")
    ap.add_argument("--text", default="red cube")
    ap.add_argument("--size", default="400x300", help="WxH of each panel")
    ap.add_argument("--eye", type=float, nargs=3, default=EYE, metavar=("X", "Y", "Z"))
    ap.add_argument("--target", type=float, nargs=3, default=TARGET, metavar=("X", "Y", "Z"))
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "images" / "demo_query.png")
    a = ap.parse_args(argv)
    w, h = (int(v) for v in a.size.lower().split("x"))
    cam = CameraSpec.look_at(eye=a.eye, target=a.target, up=(0, 0, 1), width=w, height=h)
    img = picture(a.models, a.scene, a.text, cam)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    save_small_png(a.out, img)
    print(f"wrote {a.out} ({img.shape[1]}x{img.shape[0]}, {a.out.stat().st_size // 1024} KiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
