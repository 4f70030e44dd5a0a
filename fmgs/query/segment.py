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
        image, alpha = _render_dots(engine, dots, camera)
        pix = pixel_labels(image, alpha, min_alpha).cpu()  # labelled where rendered: only [H,W] crosses
    return Segmentation(gi, gl, pix)


def _render_dots(engine, dots: torch.Tensor, camera: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """([H,W,n], [H,W]) float32 on the engine's device."""
    out = rasterize(*engine.geometry, dots.to(engine.geometry[0]), camera, backend=engine.cfg.backend)
    return out.image.float(), out.alpha.float()


def pixel_labels(dots: torch.Tensor, alpha: torch.Tensor, min_alpha: float = 0.1) -> torch.Tensor:
    """[H,W] int32 argmax of rendered class dots [H,W,n], -1 where alpha [H,W] < min_alpha."""
    pix = dots.argmax(-1).to(torch.int32)
    pix[alpha < min_alpha] = -1
    return pix


@torch.no_grad()
def class_dots(engine, classes: torch.Tensor, camera: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """The rendered dots of unit class embeddings [n,D] for ``camera`` ([H,W,n] float32, the embedded
    Gaussians' dots blended as ``segment`` blends them) and the embedded Gaussians' alpha [H,W], on the
    host."""
    v = engine.unit(classes, "class embeddings")
    rows = None if engine.index.exact else visible(*engine.geometry, camera, backend=engine.cfg.backend)
    image, alpha = _render_dots(engine, engine.channels(v, rows), camera)
    return image.cpu(), alpha.cpu()
