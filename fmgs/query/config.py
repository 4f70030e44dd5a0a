"""Query-state settings, kept free of heavy imports (server flags and config files are built from them)."""

from __future__ import annotations

from dataclasses import dataclass

POINT_CHUNK = 8192
"""Points through the field at once in a point query: bounds its working memory whatever the number of
points (the memory per point in flight: benchmarks/results/TUNING.md)."""


@dataclass(frozen=True)
class IndexConfig:
    """How a scene's embeddings are held for queries."""

    rank: int = 64
    """Basis size of the compact path (int8 coefficients: r bytes per Gaussian); 0 keeps exact float32."""
    rank2: int = 256
    """Total rank of the compact state's two tiers at most (fmgs.query.state; capped at the embeddings'
    numerical rank). The second tier, r2 - rank bytes per Gaussian memory-mapped, is read only for rows
    the first leaves unsettled (CLIP-like and absent queries); 0: no second tier (those rows go straight
    to the float16 embeddings, 2*D bytes each)."""
    exact_below: int = 200_000
    """Scenes with fewer embedded Gaussians use the exact path (4*D bytes per Gaussian)."""
    rerank: int = 4
    """The compact path first rescores the rerank * k candidates of highest upper bound (at least k, at
    most k + 2048: fmgs.query.tuning.REFINE_ABOVE), then as many more as the certificate needs: a speed
    knob, the answer is exact for every value (the figures that chose 4: benchmarks/results/TUNING.md)."""
    basis_sample: int = 100_000
    """Rows used to estimate the basis (a seeded sample; all rows when fewer)."""
    device: str = "cpu"
    """Where the query state lives. A CUDA device always holds the exact float32 embeddings (4*D bytes
    per Gaussian of device memory; the compact path is CPU-only); answers come back on the CPU."""

    def __post_init__(self) -> None:
        if min(self.rank, self.rank2, self.exact_below, self.rerank) < 0 or self.basis_sample < 1:
            raise ValueError("rank, rank2, exact_below and rerank must be >= 0, basis_sample >= 1")
