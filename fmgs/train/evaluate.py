"""Held-out evaluation of a 3DGS scene: PSNR and SSIM per view, JSON, a table and side-by-side images."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fmgs.data import HOLDOUT_EVERY
from fmgs.data.dataset import PosedDataset
from fmgs.gaussians import GaussianSet
from fmgs.io.atomic import atomic_path
from fmgs.metrics import psnr, ssim
from fmgs.render.rgb import render_rgb


@dataclass
class EvalResult:
    psnr: float
    """Mean PSNR (dB) over the held-out views."""
    ssim: float
    """Mean SSIM over the held-out views."""
    per_view: list[dict]
    """name, psnr, ssim of each view."""

    def table(self) -> str:
        rows = ["| view | PSNR dB | SSIM |", "|---|---:|---:|"]
        rows += [f"| {v['name']} | {v['psnr']:.2f} | {v['ssim']:.4f} |" for v in self.per_view]
        rows.append(f"| **mean** | **{self.psnr:.2f}** | **{self.ssim:.4f}** |")
        return "\n".join(rows)


def evaluate(
    gaussians: GaussianSet,
    ds: PosedDataset,
    out_dir: str | Path | None = None,
    scale: float = 1.0,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    holdout_every: int = HOLDOUT_EVERY,
    backend: str = "auto",
    progress: bool = False,
) -> EvalResult:
    """Render every held-out frame, compare with its photo; optionally write results into ``out_dir``.

    ``progress`` shows a bar over the views (stderr)."""
    from PIL import Image
    from tqdm.auto import tqdm

    _, test = ds.split(holdout_every)
    if not test:
        raise ValueError("no held-out frames (holdout_every < 2 or too few images)")
    dev = gaussians.means.device
    bg = torch.tensor(background, dtype=torch.float32, device=dev)
    rows = []
    if out_dir is not None:
        (Path(out_dir) / "renders").mkdir(parents=True, exist_ok=True)
    for i in tqdm(test, desc="eval-gs", unit="view", disable=not progress, leave=False):
        img, cam = ds.image(i, scale)
        with torch.no_grad():
            out = render_rgb(gaussians, cam, background=bg, backend=backend).image.clamp(0, 1).cpu()
        rows.append({"name": ds.frames[i].name, "psnr": psnr(out, img), "ssim": float(ssim(out, img))})
        if out_dir is not None:
            pair = torch.cat([img, out], 1).numpy()  # ground truth | render
            name = Path(ds.frames[i].name).stem + ".png"
            Image.fromarray((pair * 255 + 0.5).astype(np.uint8)).save(Path(out_dir) / "renders" / name)
    res = EvalResult(
        float(np.mean([r["psnr"] for r in rows])), float(np.mean([r["ssim"] for r in rows])), rows
    )
    if out_dir is not None:
        with atomic_path(Path(out_dir) / "eval.json") as tmp:
            tmp.write_text(
                json.dumps({"psnr": res.psnr, "ssim": res.ssim, "scale": scale, "views": rows}, indent=1)
            )
        with atomic_path(Path(out_dir) / "eval.md") as tmp:
            tmp.write_text(res.table() + "\n")
    return res
