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

LOW_VIEW_PSNR_DB = 20.0
"""A held-out view below this PSNR is marked: the geometry fails from there (floaters in front of the camera,
a backdrop it explains with Gaussians, a side no training view saw), whatever the mean says."""


@dataclass
class EvalResult:
    psnr: float
    """Mean PSNR (dB) over the held-out views."""
    ssim: float
    """Mean SSIM over the held-out views."""
    per_view: list[dict]
    """name, psnr, ssim of each view."""

    @property
    def worst(self) -> dict:
        """The held-out view of lowest PSNR (name, psnr, ssim)."""
        return min(self.per_view, key=lambda v: v["psnr"])

    def below(self, threshold_db: float = LOW_VIEW_PSNR_DB) -> list[dict]:
        """The held-out views under ``threshold_db``, worst first."""
        return sorted((v for v in self.per_view if v["psnr"] < threshold_db), key=lambda v: v["psnr"])

    def table(self, threshold_db: float = LOW_VIEW_PSNR_DB) -> str:
        rows = ["| view | PSNR dB | SSIM |", "|---|---:|---:|"]
        for v in self.per_view:
            mark = f" **below {threshold_db:g} dB**" if v["psnr"] < threshold_db else ""
            rows.append(f"| {v['name']}{mark} | {v['psnr']:.2f} | {v['ssim']:.4f} |")
        rows.append(f"| **mean** | **{self.psnr:.2f}** | **{self.ssim:.4f}** |")
        w = self.worst
        rows.append(f"| **worst** ({w['name']}) | **{w['psnr']:.2f}** | **{w['ssim']:.4f}** |")
        return "\n".join(rows)

    def summary(self, threshold_db: float = LOW_VIEW_PSNR_DB) -> dict:
        """The scores as JSON: means, every view, the worst view and the views below ``threshold_db``."""
        return {
            "psnr": self.psnr,
            "ssim": self.ssim,
            "per_view": self.per_view,
            "worst": self.worst,
            "threshold_db": threshold_db,
            "below": [v["name"] for v in self.below(threshold_db)],
        }

    def warning(self, threshold_db: float = LOW_VIEW_PSNR_DB) -> str | None:
        """A sentence naming each held-out view below ``threshold_db`` (None when there is none)."""
        low = self.below(threshold_db)
        if not low:
            return None
        named = ", ".join(f"{v['name']} ({v['psnr']:.1f} dB)" for v in low)
        return (
            f"{len(low)} of {len(self.per_view)} held-out views are below {threshold_db:g} dB "
            f"(mean {self.psnr:.1f} dB): {named}. Queries seen from there will miss: look at those views "
            "(eval-gs --out writes side-by-side renders) for floaters in front of the camera, a backdrop the "
            "dataset does not declare (transforms.json 'background'), or sides no training view saw."
        )


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
            doc = _strict({**res.summary(), "scale": scale, "views": rows})
            tmp.write_text(json.dumps(doc, indent=1, allow_nan=False))
        with atomic_path(Path(out_dir) / "eval.md") as tmp:
            tmp.write_text(res.table() + "\n")
    return res


def _strict(x):
    """``x`` with each non-finite float as strict JSON allows: the PSNR of a view rendered exactly
    (+inf) as the string "inf", as shards.json writes its open cells ("-inf" likewise), NaN as null."""
    if isinstance(x, float) and not np.isfinite(x):
        return None if np.isnan(x) else ("inf" if x > 0 else "-inf")
    if isinstance(x, dict):
        return {k: _strict(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_strict(v) for v in x]
    return x
