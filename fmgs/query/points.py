"""Point queries: relevancy at arbitrary 3D points through the hash grid and the language head."""

from __future__ import annotations

from typing import NamedTuple

import torch

from fmgs.checks import check_finite
from fmgs.errors import ValidationError
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
def query_points(engine, points: torch.Tensor, queries: torch.Tensor, canonical: torch.Tensor) -> PointAnswer:
    """points [P,3] world, queries [T,D], canonical [C,D] (all normalised here).

    The field's table is compacted to the rows the Gaussian means touch, so far from the scene's
    Gaussians the encoding is zero and the answer reflects the head's bias only.
    """
    if engine.field is None:
        raise NoFieldError("scene", f"{engine.name!r} has no feature field; point queries need one")
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValidationError("points", f"expected [P,3], got {list(points.shape)}")
    check_finite("points", points)
    q = engine.unit(queries)
    c = engine.unit(canonical, "canonical embeddings")
    dev = next(engine.field.parameters()).device
    f = engine.field(points.to(dev, torch.float32), dino=False).clip.float().cpu()  # [P,D]
    sim = q @ f.T  # [T,P]
    return PointAnswer(relevancy(sim, (f @ c.T)[None].expand(len(q), -1, -1), TEMPERATURE), sim)
