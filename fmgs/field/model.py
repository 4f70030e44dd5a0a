"""The feature field: hash encoding at a point, then a language (CLIP) head and an optional DINO head.

The language head's output is unit-normalised per point (per Gaussian), as in FMGS; the DINO head's is
not. ``PerGaussianFeatures`` is the ablation that replaces the field by free per-Gaussian vectors.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from fmgs.field.bounds import SceneBounds
from fmgs.field.config import FieldConfig
from fmgs.field.hashgrid import Corners, HashGrid
from fmgs.vecmath import safe_normalize


class FieldOutput(NamedTuple):
    """Decoded features at N points."""

    clip: torch.Tensor
    """[N, clip_dim] unit-norm language embeddings."""
    dino: torch.Tensor | None
    """[N, dino_dim] DINO features, or None without a DINO head."""


def mlp(d_in: int, hidden: int, layers: int, d_out: int) -> nn.Sequential:
    """``layers`` hidden ReLU layers of width ``hidden`` then a linear output."""
    mods: list[nn.Module] = []
    d = d_in
    for _ in range(layers):
        mods += [nn.Linear(d, hidden), nn.ReLU()]
        d = hidden
    mods.append(nn.Linear(d, d_out))
    return nn.Sequential(*mods)


class FeatureField(nn.Module):
    """Hash grid + heads over a bounded scene."""

    def __init__(self, cfg: FieldConfig, bounds: SceneBounds, grid: HashGrid) -> None:
        super().__init__()
        self.cfg = cfg
        self.bounds = bounds
        self.grid = grid
        self.clip_head = mlp(cfg.grid.out_dim, cfg.clip_hidden, cfg.clip_layers, cfg.clip_dim)
        self.dino_head = (
            mlp(cfg.grid.out_dim, cfg.dino_hidden, cfg.dino_layers, cfg.dino_dim) if cfg.dino_dim else None
        )

    @classmethod
    def for_points(
        cls, cfg: FieldConfig, points: torch.Tensor, bounds: SceneBounds | None = None, seed: int = 0
    ) -> FeatureField:
        """A field whose table is compacted to the rows that points [N,3] (world) touch."""
        g = torch.Generator().manual_seed(seed)
        torch.manual_seed(seed)  # the heads' default initialisers draw from the global generator
        bounds = bounds or SceneBounds.around(points)
        grid = HashGrid.compact(cfg.grid, bounds.normalise(points.to(torch.float64)), generator=g)
        return cls(cfg, bounds, grid)

    def lookup(self, points: torch.Tensor) -> Corners:
        """Table rows and weights for world points [N,3] (cache this for fixed points)."""
        return self.grid.lookup(self.bounds.normalise(points))

    def decode(self, look: Corners, dino: bool = True) -> FieldOutput:
        """Features at looked-up points."""
        return self.heads(self.grid.encode(look), dino)

    def heads(self, h: torch.Tensor, dino: bool = True) -> FieldOutput:
        """Features from encodings h [N, L*F]."""
        clip = safe_normalize(self.clip_head(h))
        d = self.dino_head(h) if (dino and self.dino_head is not None) else None
        return FieldOutput(clip, d)

    def forward(self, points: torch.Tensor, dino: bool = True) -> FieldOutput:
        """Features at world points [N,3]."""
        return self.decode(self.lookup(points), dino)


class PerGaussianFeatures(nn.Module):
    """Ablation: a free embedding per Gaussian instead of the field (no sharing between Gaussians)."""

    def __init__(self, n: int, clip_dim: int, dino_dim: int, seed: int = 0) -> None:
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.clip = nn.Parameter(torch.randn(n, clip_dim, generator=g) * 0.1)
        self.dino = nn.Parameter(torch.randn(n, dino_dim, generator=g) * 0.1) if dino_dim else None

    def decode_index(self, idx: torch.Tensor, dino: bool = True) -> FieldOutput:
        """Features of Gaussians idx [M]."""
        d = self.dino[idx] if (dino and self.dino is not None) else None
        return FieldOutput(safe_normalize(self.clip[idx]), d)
