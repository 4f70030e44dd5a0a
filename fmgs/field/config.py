"""Settings of the feature field: the hash encoding, the heads, which Gaussians carry features.

Kept free of torch so that command-line flags and config files can be built from them cheaply.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field


@dataclass(frozen=True)
class HashGridConfig:
    """Shape of the encoding (defaults: the FMGS paper)."""

    levels: int = 24
    """Number of resolution levels."""
    min_res: int = 16
    """Resolution of the coarsest level (cells per unit)."""
    max_res: int = 512
    """Resolution of the finest level."""
    log2_table: int = 20
    """log2 of the hash table size per level (T)."""
    features: int = 8
    """Features per table entry (F); the encoding has levels * features dims."""
    init_scale: float = 1e-4
    """Table entries start uniform in [-init_scale, init_scale]."""

    def __post_init__(self) -> None:
        if self.levels < 1 or self.features < 1 or not 1 <= self.min_res <= self.max_res:
            raise ValueError("need levels >= 1, features >= 1 and 1 <= min_res <= max_res")
        if not 4 <= self.log2_table <= 30:
            raise ValueError("log2_table must lie in [4, 30]")

    @property
    def out_dim(self) -> int:
        return self.levels * self.features

    def resolutions(self) -> list[int]:
        """Cells per unit at each level."""
        if self.levels == 1:
            return [self.min_res]
        b = math.exp((math.log(self.max_res) - math.log(self.min_res)) / (self.levels - 1))
        # The small epsilon keeps floor(min_res * b^(L-1)) == max_res despite rounding of b.
        return [math.floor(self.min_res * b**level + 1e-6) for level in range(self.levels)]

    def level_sizes(self) -> list[int]:
        """Rows per level: the dense vertex count when it fits T, else T."""
        T = 1 << self.log2_table
        return [min((r + 1) ** 3, T) for r in self.resolutions()]

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class FieldConfig:
    """Encoding and head sizes (defaults: the FMGS paper and its reference code)."""

    grid: HashGridConfig = field(default_factory=HashGridConfig)
    """The hash encoding."""
    clip_dim: int = 512
    """Language embedding size (the text encoder's dim)."""
    clip_hidden: int = 256
    """Width of the language head's hidden layers."""
    clip_layers: int = 4
    """Hidden layers in the language head."""
    dino_dim: int = 384
    """DINO feature size; 0 means no DINO head."""
    dino_hidden: int = 256
    """Width of the DINO head's hidden layer(s)."""
    dino_layers: int = 1
    """Hidden layers in the DINO head."""

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> FieldConfig:
        d = dict(d)
        d["grid"] = HashGridConfig(**d["grid"])
        return cls(**d)


SELECT_RULES = ("coverage", "paper")


@dataclass(frozen=True)
class SelectConfig:
    """Which Gaussians carry features (fmgs.field.select)."""

    rule: str = "coverage"
    """"coverage": in every pixel of every training view (at the target-map resolution), the Gaussians
    that make up the first ``coverage`` of its blending weight, heaviest first; "paper": the FMGS
    reference code's opacity and radius tests, which left a thin object's Gaussians (a pencil, IoU 0.00)
    without features."""
    coverage: float = 0.9
    """Share of each pixel's blending weight the kept Gaussians make up at least (rule "coverage")."""
    opacity_min: float = 0.25
    """Rule "paper": keep Gaussians with opacity above this ..."""
    radius_min: float = 2.0
    """... whose projected 3-sigma radius exceeds this many pixels in at least one training view."""
    max_selected: int | None = None
    """At most this many Gaussians carry features: of those the rule keeps, the ones with the largest
    blending weight summed over all pixels of the training views; none: no cap. Caps a package's
    embeddings and the field's training cost."""

    def __post_init__(self) -> None:
        if self.rule not in SELECT_RULES:
            raise ValueError(f"select rule must be one of {SELECT_RULES}, got {self.rule!r}")
        if not 0.0 < self.coverage <= 1.0:
            raise ValueError(f"coverage must lie in (0, 1], got {self.coverage}")
        if self.max_selected is not None and self.max_selected < 1:
            raise ValueError(f"max_selected must be at least 1 (or none), got {self.max_selected}")
