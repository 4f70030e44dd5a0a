"""Point queries: relevancy at arbitrary 3D points through the hash grid and the language head."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch

from fmgs.checks import check_finite
from fmgs.errors import ValidationError
from fmgs.query.config import POINT_CHUNK
from fmgs.query.relevancy import TEMPERATURE, relevancy


class PointAnswer(NamedTuple):
    """Relevancy of P points for T queries."""

    relevancy: torch.Tensor
    """[T,P] float32."""
    similarity: torch.Tensor
    """[T,P] float32 f(x).q."""


class NoFieldError(ValidationError):
    """The scene package holds no feature field (per-Gaussian packages)."""


@torch.no_grad()
def query_points(
    engine,
    points: torch.Tensor,
    queries: torch.Tensor,
    canonical: torch.Tensor,
    chunk: int = POINT_CHUNK,
    between_chunks: Callable[[], None] | None = None,
) -> PointAnswer:
    """points [P,3] world, queries [T,D], canonical [C,D] (all normalised here).

    Points go through the field ``chunk`` at a time into preallocated [T,P] answers, so the working
    memory is bounded by the chunk, not by P; ``between_chunks`` runs after each (a server stops a
    request whose deadline has passed there by raising). The field's table is compacted to the rows the
    Gaussian means touch, so far from the scene's Gaussians the encoding is zero and the answer reflects
    the head's bias only.
    """
    if engine.field is None:
        raise NoFieldError("scene", f"{engine.name!r} has no feature field; point queries need one")
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValidationError("points", f"expected [P,3], got {list(points.shape)}")
    check_finite("points", points)
    q = engine.unit(queries)
    c = engine.unit(canonical, "canonical embeddings")
    if chunk < 1:
        raise ValidationError("chunk", f"must be >= 1, got {chunk}")
    dev = next(engine.field.parameters()).device
    P = points.shape[0]
    rel = torch.empty(len(q), P, dtype=torch.float32)
    sim = torch.empty(len(q), P, dtype=torch.float32)
    for s in range(0, P, chunk):
        f = engine.field(points[s : s + chunk].to(dev, torch.float32), dino=False).clip.float().cpu()  # [p,D]
        d = q @ f.T  # [T,p]
        sim[:, s : s + chunk] = d
        rel[:, s : s + chunk] = relevancy(d, (f @ c.T)[None].expand(len(q), -1, -1), TEMPERATURE)
        if between_chunks is not None:
            between_chunks()
    return PointAnswer(rel, sim)
