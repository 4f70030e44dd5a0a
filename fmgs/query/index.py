"""The per-Gaussian query state of a scene: compact scores for every embedded Gaussian, exact re-ranking.

Exact path (small scenes, or ``rank=0``): the stored embeddings [M,D] as float32; a query is one
matrix-vector product. Compact path (large scenes): a rank-r basis B [r,D] of the scene's embeddings
(top eigenvectors of E^T E) and coefficients E B^T [M,r] quantised to int8 with one scale per basis
vector, so a query reads r bytes per Gaussian (a numba kernel); the best ``rerank * k`` candidates are
then rescored exactly from the full embeddings, memory-mapped from the package, so the returned scores
are exact and the ranking is exact whenever the true top-k lie among the candidates (measured in
benchmarks/server.py).

Scores: relevancy = min_n sigmoid(t (f.q - f.c_n)) = sigmoid(t (f.q - max_n f.c_n)); Gaussians are ranked
by the exact margin f.q - max_n f.c_n (ties by index), which orders them as relevancy does but never
saturates.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch

from fmgs.query.config import IndexConfig
from fmgs.query.relevancy import TEMPERATURE


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
        scales: torch.Tensor | None = None,
    ) -> None:
        self.coeffs = coeffs
        """[M,r] int8 coefficients (float32 embeddings on the exact path, r = D)."""
        self.basis = basis
        """[r,D] float32 orthonormal rows, or None on the exact path."""
        self.scales = scales
        """[r] float32 dequantisation scale per basis vector (compact path)."""
        self.canonical = canonical
        """[M,C] float32 dot products with the scene's canonical phrases (exact, from the package)."""
        self.canonical_max = (
            canonical.amax(1) if canonical.shape[1] else torch.zeros(len(canonical), device=canonical.device)
        )
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
        dev = torch.device(cfg.device)
        if dev.type != "cpu":
            return cls(_float32_on(embeddings, dev), None, canonical.float().to(dev), None, cfg)
        canonical = canonical.float().contiguous()
        if cfg.rank == 0 or cfg.rank >= D or M < cfg.exact_below:
            return cls(embeddings.float().contiguous(), None, canonical, None, cfg)
        basis = _basis(embeddings, cfg.rank, cfg.basis_sample)
        coeffs, scales = _quantise(embeddings, basis)
        if read_rows is None:
            src = embeddings

            def read_rows(rows: np.ndarray) -> torch.Tensor:
                return src[torch.from_numpy(rows)].float()

        return cls(coeffs, basis, canonical, read_rows, cfg, scales)

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

    @property
    def device(self) -> torch.device:
        return self.coeffs.device

    def dots(self, vectors: torch.Tensor, shift: torch.Tensor | None = None) -> torch.Tensor:
        """[M,n] f.v - shift for unit vectors [n,D] (compact approximation on the compact path).

        shift [M] (default 0) is subtracted from every column, fused into the kernel. The result lives
        on the index's device.
        """
        v = vectors.float().to(self.device)
        if self.basis is None:
            d = self.coeffs @ v.T
            return d if shift is None else d - shift[:, None]
        from fmgs.query.kernels import int8_dots

        W = ((v @ self.basis.T) * self.scales).T.contiguous()  # [r,n]
        out = np.empty((self.num, len(v)), np.float32)
        sh = np.zeros(self.num, np.float32) if shift is None else shift.float().contiguous().numpy()
        int8_dots(self.coeffs.numpy(), W.numpy(), sh, out)
        return torch.from_numpy(out)

    def exact_dots(self, rows: torch.Tensor, vectors: torch.Tensor) -> torch.Tensor:
        """[k,n] exact f.v for rows [k] (any order)."""
        if self.basis is None:
            return self.coeffs[rows.to(self.device)] @ vectors.float().to(self.device).T
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
        vecs = vecs.float().to(self.device)
        if canonical_vectors is None and not self.exact:  # margin f.q - max_n f.c_n from the kernel
            margin = self.dots(vecs, self.canonical_max)[:, 0]
            d = None
        elif canonical_vectors is None:
            d = self.dots(vecs)
            margin = d[:, 0] - self.canonical_max
        else:
            d = self.dots(vecs)  # [M, 1+C]
            margin = d[:, 0] - d[:, 1:].amax(1)
        n_cand = k if (self.exact or self.cfg.rerank == 0) else min(M, self.cfg.rerank * k)
        cand = torch.topk(margin, n_cand, sorted=False).indices
        if self.exact or self.cfg.rerank == 0:
            m = margin[cand]
            sim = m + self.canonical_max[cand] if d is None else d[cand, 0]
        else:
            ex = self.exact_dots(cand, vecs)
            sim = ex[:, 0]
            m = sim - (self.canonical_max[cand] if canonical_vectors is None else ex[:, 1:].amax(1))
        order = _order(m, cand)[:k]
        rows, sim, m = cand[order], sim[order], m[order]
        rel = torch.sigmoid(TEMPERATURE * m)
        keep = rel >= threshold
        return Ranked(rows[keep].cpu(), rel[keep].cpu(), sim[keep].cpu())


def _float32_on(embeddings: torch.Tensor, device: torch.device, step: int = 1 << 18) -> torch.Tensor:
    """[M,D] float32 copy of embeddings on ``device``, converted there chunk by chunk (no host-side
    float32 copy of a memory-mapped float16 table)."""
    out = torch.empty(embeddings.shape, dtype=torch.float32, device=device)
    for s in range(0, embeddings.shape[0], step):
        out[s : s + step] = embeddings[s : s + step].to(device, non_blocking=False)
    return out


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


def _quantise(embeddings: torch.Tensor, basis: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """int8 coefficients [M,r] and per-basis-vector scales [r] of E B^T (two chunked passes)."""
    M, r = embeddings.shape[0], basis.shape[0]
    step = 65536
    amax = torch.zeros(r)
    for s in range(0, M, step):  # never a full float32 copy of [M,D]
        amax = torch.maximum(amax, (embeddings[s : s + step].float() @ basis.T).abs().amax(0))
    scales = (amax / 127).clamp_min(1e-30)
    q = torch.empty(M, r, dtype=torch.int8)
    for s in range(0, M, step):
        c = embeddings[s : s + step].float() @ basis.T
        q[s : s + step] = (c / scales).round().clamp(-127, 127).to(torch.int8)
    return q, scales


def int8_dots_reference(coeffs: torch.Tensor, scales: torch.Tensor, basis: torch.Tensor, v: torch.Tensor):
    """Twin of the kernel path of ``EmbeddingIndex.dots``: [M,n] (dequantised coefficients) . (B v)."""
    return (coeffs.float() * scales) @ (v.float() @ basis.T).T


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
