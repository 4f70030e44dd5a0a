"""The per-Gaussian query state of a scene: compact scores for every embedded Gaussian, exact re-ranking.

Exact path (small scenes, or ``rank=0``): the stored embeddings [M,D] as float32; a query is one
matrix-vector product. Compact path (large scenes): a rank-r basis B [r,D] of the scene's embeddings
(top eigenvectors of E^T E) and coefficients E B^T [M,r] in float32, so a query costs r/D of the exact
product and 4r bytes per Gaussian; the best ``rerank * k`` candidates are then rescored exactly from the
full embeddings, memory-mapped from the package, so the returned scores are exact and the ranking is
exact whenever the true top-k lie among the candidates (measured in benchmarks/query.py).

Scores: relevancy = min_n sigmoid(t (f.q - f.c_n)) = sigmoid(t (f.q - max_n f.c_n)); Gaussians are ranked
by the exact margin f.q - max_n f.c_n (ties by index), which orders them as relevancy does but never
saturates.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from fmgs.query.relevancy import TEMPERATURE


@dataclass(frozen=True)
class IndexConfig:
    """How a scene's embeddings are held for queries."""

    rank: int = 32
    """Basis size of the compact path; 0 keeps the exact float32 embeddings."""
    exact_below: int = 200_000
    """Scenes with fewer embedded Gaussians use the exact path (4*D bytes per Gaussian)."""
    rerank: int = 4
    """The compact path rescores rerank * k candidates exactly (0: return the compact scores)."""
    basis_sample: int = 100_000
    """Rows used to estimate the basis (a seeded sample; all rows when fewer)."""

    def __post_init__(self) -> None:
        if self.rank < 0 or self.exact_below < 0 or self.rerank < 0 or self.basis_sample < 1:
            raise ValueError("rank, exact_below and rerank must be >= 0, basis_sample >= 1")


class Ranked(NamedTuple):
    """Rows of the embedded Gaussians, best first."""

    rows: torch.Tensor
    """[K] int64 rows into the embedded Gaussians (not scene indices)."""
    relevancy: torch.Tensor
    """[K] float32 relevancy in (0,1)."""
    similarity: torch.Tensor
    """[K] float32 f.q."""


RowReader = Callable[[np.ndarray], torch.Tensor]
"""Exact embeddings for sorted unique rows [k] -> [k,D] float32."""


class EmbeddingIndex:
    """Scores every embedded Gaussian against query vectors; see the module docstring."""

    def __init__(
        self,
        coeffs: torch.Tensor,
        basis: torch.Tensor | None,
        canonical: torch.Tensor,
        read_rows: RowReader | None,
        cfg: IndexConfig,
    ) -> None:
        self.coeffs = coeffs
        """[M,r] float32 coefficients (the embeddings themselves on the exact path, r = D)."""
        self.basis = basis
        """[r,D] float32 orthonormal rows, or None on the exact path."""
        self.canonical = canonical
        """[M,C] float32 dot products with the scene's canonical phrases (exact, from the package)."""
        self.canonical_max = canonical.amax(1) if canonical.shape[1] else torch.zeros(len(canonical))
        """[M] the largest canonical dot per Gaussian."""
        self.read_rows = read_rows
        self.cfg = cfg

    @classmethod
    def build(
        cls,
        embeddings: torch.Tensor,
        canonical: torch.Tensor,
        cfg: IndexConfig = IndexConfig(),
        read_rows: RowReader | None = None,
    ) -> EmbeddingIndex:
        """From embeddings [M,D] (any float dtype) and canonical dots [M,C].

        ``read_rows`` supplies exact rows for re-ranking on the compact path (default: slices of
        ``embeddings``, which then stay referenced).
        """
        M, D = embeddings.shape
        canonical = canonical.float().contiguous()
        if cfg.rank == 0 or cfg.rank >= D or M < cfg.exact_below:
            return cls(embeddings.float().contiguous(), None, canonical, None, cfg)
        basis = _basis(embeddings, cfg.rank, cfg.basis_sample)
        coeffs = torch.empty(M, cfg.rank)
        for s in range(0, M, 65536):  # chunked: never a full float32 copy of [M,D]
            coeffs[s : s + 65536] = embeddings[s : s + 65536].float() @ basis.T
        if read_rows is None:
            src = embeddings

            def read_rows(rows: np.ndarray) -> torch.Tensor:
                return src[torch.from_numpy(rows)].float()

        return cls(coeffs, basis, canonical, read_rows, cfg)

    @property
    def exact(self) -> bool:
        return self.basis is None

    @property
    def num(self) -> int:
        return int(self.coeffs.shape[0])

    def nbytes(self) -> int:
        """Bytes of the in-memory state (coefficients, basis, canonical dots)."""
        t = [self.coeffs, self.canonical, self.canonical_max] + (
            [self.basis] if self.basis is not None else []
        )
        return sum(x.numel() * x.element_size() for x in t)

    def dots(self, vectors: torch.Tensor) -> torch.Tensor:
        """[M,n] f.v for unit vectors [n,D] (compact approximation on the compact path)."""
        v = vectors.float()
        if self.basis is not None:
            v = v @ self.basis.T  # [n,r]
        return self.coeffs @ v.T

    def exact_dots(self, rows: torch.Tensor, vectors: torch.Tensor) -> torch.Tensor:
        """[k,n] exact f.v for rows [k] (any order)."""
        if self.basis is None:
            return self.coeffs[rows] @ vectors.float().T
        r = rows.numpy()
        uniq, inv = np.unique(r, return_inverse=True)
        return (self.read_rows(uniq) @ vectors.float().T)[torch.from_numpy(inv)]

    def rank(
        self,
        query: torch.Tensor,
        top_k: int,
        threshold: float = 0.0,
        canonical_vectors: torch.Tensor | None = None,
    ) -> Ranked:
        """Best ``top_k`` rows for a unit query [D] with relevancy >= threshold.

        canonical_vectors [C,D] replace the scene's canonical phrases (None: the stored dots).
        """
        M = self.num
        k = max(0, min(int(top_k), M))
        if k == 0:
            e = torch.zeros(0)
            return Ranked(torch.zeros(0, dtype=torch.int64), e, e)
        vecs = query[None] if canonical_vectors is None else torch.cat([query[None], canonical_vectors])
        d = self.dots(vecs)  # [M, 1 or 1+C]
        cmax = self.canonical_max if canonical_vectors is None else d[:, 1:].amax(1)
        margin = d[:, 0] - cmax
        n_cand = k if (self.exact or self.cfg.rerank == 0) else min(M, self.cfg.rerank * k)
        cand = torch.topk(margin, n_cand, sorted=False).indices
        if self.exact or self.cfg.rerank == 0:
            sim, m = d[cand, 0], margin[cand]
        else:
            ex = self.exact_dots(cand, vecs)
            sim = ex[:, 0]
            m = sim - (self.canonical_max[cand] if canonical_vectors is None else ex[:, 1:].amax(1))
        order = _order(m, cand)[:k]
        rows, sim, m = cand[order], sim[order], m[order]
        rel = torch.sigmoid(TEMPERATURE * m)
        keep = rel >= threshold
        return Ranked(rows[keep], rel[keep], sim[keep])


def rank_reference(
    embeddings: torch.Tensor, canonical: torch.Tensor, query: torch.Tensor, top_k: int, threshold: float = 0.0
) -> Ranked:
    """Exact twin of ``EmbeddingIndex.rank``: embeddings [M,D] (float32), canonical dots [M,C], query [D]."""
    sim = embeddings.float() @ query.float()
    m = sim - (canonical.float().amax(1) if canonical.shape[1] else 0.0)
    rows = torch.arange(len(sim))
    order = _order(m, rows)[: max(0, min(int(top_k), len(sim)))]
    rel = torch.sigmoid(TEMPERATURE * m[order])
    keep = rel >= threshold
    return Ranked(rows[order][keep], rel[keep], sim[order][keep])


def _order(margin: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """Positions sorting by margin descending, ties by row ascending (reproducible)."""
    by_row = torch.argsort(rows)
    return by_row[torch.sort(margin[by_row], descending=True, stable=True).indices]


def _basis(embeddings: torch.Tensor, rank: int, sample: int) -> torch.Tensor:
    """[rank,D] top eigenvectors of E^T E (best rank-r subspace for dot products), from a seeded sample."""
    M = embeddings.shape[0]
    if M > sample:
        g = torch.Generator().manual_seed(0)
        rows = torch.randperm(M, generator=g)[:sample].sort().values
        E = embeddings[rows].double()
    else:
        E = embeddings.double()
    _, vecs = torch.linalg.eigh(E.T @ E)  # ascending eigenvalues
    return vecs[:, -rank:].flip(1).T.float().contiguous()
