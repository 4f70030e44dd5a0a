"""Open-vocabulary segmentation (3D-OVS protocol): cosine to class names, softmax, argmax.

Softmax does not change the argmax, so labels are the argmax of the dot products; per pixel the class
dots are rendered (dot-then-render) and pixels the embedded Gaussians barely cover get -1. The dots are
the stored embeddings' exact dots on every path (SceneEngine.channels), so labels do not depend on the
scene's size or the device.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from fmgs.cameras import Camera
from fmgs.render import rasterize, visible


class Segmentation(NamedTuple):
    """Labels for a list of classes."""

    gaussian_index: torch.Tensor | None
    """[M] int64 scene indices of the embedded Gaussians."""
    gaussian_labels: torch.Tensor | None
    """[M] int32 class of each embedded Gaussian."""
    pixel_labels: torch.Tensor | None
    """[H,W] int32 class per pixel, -1 where alpha < min_alpha."""


@torch.no_grad()
def segment(
    engine, classes: torch.Tensor, camera: Camera | None, per_gaussian: bool, min_alpha: float = 0.1
) -> Segmentation:
    """Labels for unit class embeddings [n,D] (n >= 1)."""
    v = engine.unit(classes, "class embeddings")
    rows = None  # every row's exact dots (per-Gaussian labels, or the exact float32 table)
    if not per_gaussian and not engine.index.exact:  # only the Gaussians the view can touch
        no_view = torch.zeros(engine.num_embedded, dtype=torch.bool)
        rows = no_view if camera is None else visible(*engine.geometry, camera, backend=engine.cfg.backend)
    dots = engine.channels(v, rows)  # [M,n]
    gi = gl = pix = None
    if per_gaussian:
        gi, gl = engine.selected.clone(), dots.argmax(1).to(torch.int32).cpu()
    if camera is not None:
        out = rasterize(*engine.geometry, dots.to(engine.geometry[0]), camera, backend=engine.cfg.backend)
        pix = out.image.float().argmax(-1).to(torch.int32).cpu()
        pix[out.alpha.cpu() < min_alpha] = -1
    return Segmentation(gi, gl, pix)
