"""Small vector helpers that stay finite at the edges of floating point."""

from __future__ import annotations

import torch


def safe_normalize(v: torch.Tensor) -> torch.Tensor:
    """Unit vectors along the last dim, exact for denormal or huge inputs; a zero vector stays zero.

    Dividing by the largest component first keeps the squared norm away from underflow and overflow.
    """
    m = v.abs().amax(dim=-1, keepdim=True)
    v = v / torch.where(m > 0, m, torch.ones_like(m))
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(torch.finfo(v.dtype).tiny)
