"""Text queries on a loaded scene: Gaussians ranked by relevancy, and relevancy images for a camera."""

from __future__ import annotations

from typing import NamedTuple

import torch

from fmgs.cameras import Camera
from fmgs.query.relevancy import TEMPERATURE, relevancy
from fmgs.render import rasterize


class QueryResult(NamedTuple):
    """Gaussians ranked by relevancy to one query."""

    index: torch.Tensor
    """[K] int64 indices into the scene's Gaussians, most relevant first."""
    relevancy: torch.Tensor
    """[K] float32 relevancy in (0, 1)."""
    similarity: torch.Tensor
    """[K] float32 cosine similarity of the Gaussian's embedding with the query."""


def _unit(q: torch.Tensor, dim: int) -> torch.Tensor:
    from fmgs.errors import ValidationError
    from fmgs.vecmath import safe_normalize

    if q.shape != (dim,):
        raise ValidationError("query embedding", f"expected [{dim}], got {list(q.shape)}")
    if not bool(torch.isfinite(q).all()) or not bool(q.abs().max() > 0):
        raise ValidationError("query embedding", "must be finite and non-zero")
    return safe_normalize(q.float())


def rank_gaussians(scene, query: torch.Tensor, top_k: int | None = None) -> QueryResult:
    """Rank the scene's embedded Gaussians by relevancy to a query embedding [D] (normalised here).

    One matrix-vector product with the stored embeddings plus the precomputed canonical dot products.
    """
    q = _unit(query, scene.dim).to(scene.embeddings.device)
    sim = scene.embeddings @ q  # [M]
    r = relevancy(sim, scene.canonical, TEMPERATURE)
    k = len(r) if top_k is None else max(0, min(int(top_k), len(r)))
    # Ties broken by index (stable sort) so results are reproducible.
    order = torch.sort(r, descending=True, stable=True).indices[:k]
    return QueryResult(scene.selected[order], r[order], sim[order])


@torch.no_grad()
def relevancy_image(
    scene, camera: Camera, query: torch.Tensor, backend: str = "auto"
) -> tuple[torch.Tensor, torch.Tensor]:
    """([H,W] relevancy, [H,W] alpha) of a query for ``camera``, by dot-then-render.

    Blending is linear, so rendering the C+1 scalars (f.q, f.c_n) per Gaussian equals dotting the
    rendered D-dim feature (the exact twin is ``relevancy_image_reference``).
    """
    q = _unit(query, scene.dim).to(scene.embeddings.device)
    chans = torch.cat([(scene.embeddings @ q)[:, None], scene.canonical], 1)  # [M, 1+C]
    out = _render(scene, camera, chans, backend)
    return relevancy(out.image[..., 0], out.image[..., 1:], TEMPERATURE), out.alpha


@torch.no_grad()
def relevancy_image_reference(scene, camera: Camera, query: torch.Tensor, canonical_embeddings: torch.Tensor):
    """Exact twin: render the full embeddings [M,D], then dot with the query and canonical embeddings."""
    q = _unit(query, scene.dim).to(scene.embeddings.device)
    out = _render(scene, camera, scene.embeddings, "reference")
    F = out.image  # [H,W,D]
    return relevancy(F @ q, F @ canonical_embeddings.float().T, TEMPERATURE), out.alpha


def _render(scene, camera: Camera, features: torch.Tensor, backend: str):
    g = scene.gaussians.subset(scene.selected)
    return rasterize(g.means, g.quats, g.scales, g.opacities, features, camera, backend=backend)
