"""Scene bounds: world positions to the unit cube the hash grid reads, with a contraction outside."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class SceneBounds:
    """An axis-aligned box; inside it the mapping is affine, outside it contracts (mip-NeRF 360, L-inf).

    normalise(x): u = (x - center) / half; u stays where max|u| <= 1 and becomes (2 - 1/n) u / n with
    n = max|u| beyond, so all of space lands in [-2, 2]^3; then (u + 2) / 4 maps that to [0, 1]^3.
    """

    center: tuple[float, float, float]
    """Box centre (world units)."""
    half: tuple[float, float, float]
    """Box half-extent per axis (world units, positive)."""

    def __post_init__(self) -> None:
        if len(self.center) != 3 or len(self.half) != 3:
            raise ValueError("center and half need 3 values each")
        if not all(h > 0 and h < float("inf") for h in self.half):
            raise ValueError(f"half-extents must be positive and finite, got {self.half}")

    @classmethod
    def around(cls, points: torch.Tensor, pad: float = 0.02, quantile: float = 0.0) -> SceneBounds:
        """The box of points [N,3] (optionally between the quantile and 1 - quantile), padded by ``pad``
        of its size; a flat axis gets the largest axis' half-extent (or 1 when all are flat)."""
        p = points.detach().to(torch.float64)
        if p.shape[0] == 0:
            raise ValueError("cannot bound an empty point set")
        if quantile > 0:
            lo, hi = torch.quantile(p, quantile, dim=0), torch.quantile(p, 1 - quantile, dim=0)
        else:
            lo, hi = p.amin(0), p.amax(0)
        half = (hi - lo) / 2 * (1 + pad)
        big = float(half.max())
        floor = big * 1e-3 if big > 0 else 1.0
        half = half.clamp_min(floor)
        return cls(tuple(((lo + hi) / 2).tolist()), tuple(half.tolist()))

    def normalise(self, x: torch.Tensor) -> torch.Tensor:
        """[N,3] world points -> [N,3] in [0,1]^3 (differentiable; finite for any finite input)."""
        # float64 inside: a float32 point far away divided by a small half-extent cannot overflow.
        f64 = torch.float64
        c = torch.tensor(self.center, dtype=f64, device=x.device)
        h = torch.tensor(self.half, dtype=f64, device=x.device)
        u = (x.to(f64) - c) / h
        n = u.abs().amax(-1, keepdim=True)
        outside = n > 1
        n_safe = torch.where(outside, n, torch.ones_like(n))
        u = torch.where(outside, (2 - 1 / n_safe) * (u / n_safe), u)
        return ((u + 2) / 4).to(x.dtype)

    def to_dict(self) -> dict:
        return {"center": list(self.center), "half": list(self.half)}

    @classmethod
    def from_dict(cls, d: dict) -> SceneBounds:
        return cls(tuple(float(v) for v in d["center"]), tuple(float(v) for v in d["half"]))
