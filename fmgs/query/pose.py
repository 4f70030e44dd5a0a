"""Pose queries: a relevancy image for a camera by dot-then-render, optionally RGB, depth and alpha."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch

from fmgs.cameras import Camera
from fmgs.errors import ValidationError
from fmgs.query.relevancy import TEMPERATURE, relevancy
from fmgs.render import rasterize, visible
from fmgs.render.rgb import render_rgb

OUTPUTS = ("relevancy", "rgb", "depth", "alpha")
SCORE_BAND_PIXELS = 1 << 20
"""An image is scored in bands of rows of about this many pixels, a ``between`` hook called after each:
scored at once, a 4096x2160 image was the longest stretch of a render without a deadline check
(docs/serving.md has the figures)."""


class PoseRender(NamedTuple):
    """What a pose query returns (None for outputs not asked for)."""

    relevancy: torch.Tensor | None
    """[H,W] float32 relevancy in (0,1)."""
    rgb: torch.Tensor | None
    """[H,W,3] float32 colour of all Gaussians, clamped to [0,1]."""
    depth: torch.Tensor | None
    """[H,W] float32 expected depth of all Gaussians (0 where empty)."""
    alpha: torch.Tensor | None
    """[H,W] float32 accumulated opacity of the embedded Gaussians."""
    argmax: tuple[int, int, float] | None
    """(x, y, value) of the most relevant pixel (first in row-major order on ties)."""


def relevancy_layer(engine, camera: Camera, query: torch.Tensor | None, canonical=None, between_tiles=None):
    """The rasterised relevancy channels of the engine's embedded Gaussians (f.q and f.c_n per pixel,
    [H,W,1+C]) with their opacity, or only the opacity ([H,W,1] ones blended) when ``query`` is None."""
    if query is None:
        chans = torch.ones(engine.num_embedded, 1)
    else:
        # The compact path scores exactly only the Gaussians this view can touch (the rest blend nothing).
        rows = None if engine.index.exact else visible(*engine.geometry, camera, backend=engine.cfg.backend)
        chans = engine.relevancy_channels(query, canonical, rows)
    return rasterize(
        *engine.geometry, chans.to(engine.geometry[0]), camera, backend=engine.cfg.backend,
        between_tiles=between_tiles,
    )  # fmt: skip


def score_image(
    img: torch.Tensor, between: Callable[[], None] | None = None
) -> tuple[torch.Tensor, tuple[int, int, float]]:
    """Relevancy [H,W] of rendered channels [H,W,1+C] and its argmax (x, y, value), first in row-major
    order on ties. Scored in bands of whole rows of about SCORE_BAND_PIXELS, with ``between()`` after
    each (it may raise) when the image has more than one; the bands do not depend on ``between``, so the
    image is the same whether or not a caller checks a deadline (float32 sigmoids may round a band's
    last elements apart from the image scored at once)."""
    rows = max(1, SCORE_BAND_PIXELS // max(img.shape[1], 1))
    if rows >= img.shape[0]:
        rel = relevancy(img[..., 0], img[..., 1:], TEMPERATURE)
    else:
        bands = []
        for y in range(0, img.shape[0], rows):
            band = img[y : y + rows]
            bands.append(relevancy(band[..., 0], band[..., 1:], TEMPERATURE))
            if between is not None:
                between()
        rel = torch.cat(bands)
    flat = int(torch.argmax(rel))
    y, x = divmod(flat, rel.shape[1])
    return rel, (x, y, float(rel[y, x]))


@torch.no_grad()
def render_pose(
    engine,
    camera: Camera,
    query: torch.Tensor | None,
    outputs: tuple[str, ...] = ("relevancy",),
    canonical: torch.Tensor | None = None,
    between_tiles: Callable[[], None] | None = None,
) -> PoseRender:
    """Render ``outputs`` for ``camera``; query [D] (needed for relevancy), canonical [C,D] optional;
    ``between_tiles`` is called between batches of tiles (a server stops a render there once the
    client's deadline has passed by raising).

    Relevancy renders 1 + C scalar channels per embedded Gaussian (f.q and f.c_n) and applies the
    relevancy to the blend, which equals scoring the rendered D-dim feature (blending is linear).
    """
    bad = [o for o in outputs if o not in OUTPUTS]
    if bad or not outputs:
        raise ValidationError("outputs", f"choose from {OUTPUTS}, got {list(outputs)}")
    rel = alpha = rgb = depth = arg = None
    if "relevancy" in outputs or "alpha" in outputs:
        if "relevancy" in outputs and query is None:
            raise ValidationError("text", "a query is needed for a relevancy image")
        q = query if "relevancy" in outputs else None
        out = relevancy_layer(engine, camera, q, canonical, between_tiles)
        alpha = out.alpha.float().cpu()
        if "relevancy" in outputs:  # scored where it was rendered: only [H,W] crosses to the host
            rel, arg = score_image(out.image.float(), between_tiles)
            rel = rel.cpu()
    if "rgb" in outputs or "depth" in outputs:
        out = render_rgb(engine.gaussians, camera, backend=engine.cfg.backend, between_tiles=between_tiles)
        if between_tiles is not None:  # the render's per-Gaussian sums and casts after its last batch
            between_tiles()
        rgb = out.image.float().clamp(0, 1).cpu()
        depth = out.depth.float().cpu()
    want = set(outputs)
    return PoseRender(
        rel if "relevancy" in want else None,
        rgb if "rgb" in want else None,
        depth if "depth" in want else None,
        alpha if "alpha" in want else None,
        arg,
    )


@torch.no_grad()
def render_pose_reference(
    engine, camera: Camera, query: torch.Tensor, embeddings: torch.Tensor
) -> torch.Tensor:
    """Exact twin of the relevancy image: render the full embeddings [M,D], then score every pixel.

    Uses the scene's canonical dots' source: canonical embeddings are not stored, so the canonical
    channels are rendered from the stored per-Gaussian canonical dots (linear, hence exact as well).
    """
    q = engine.unit(query[None])[0]
    g = engine.geometry
    F = rasterize(*g, embeddings.float(), camera, backend="reference").image.float()  # [H,W,D]
    C = rasterize(*g, engine.index.canonical, camera, backend="reference").image.float()  # [H,W,C]
    return relevancy(F @ q, C, TEMPERATURE)
