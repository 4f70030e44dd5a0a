"""Scene embeddings and text-query sets that span what real queries look like (tests and benchmarks).

Scene: field-like unit embeddings (a random MLP over Fourier features of 3D points, rank <= 257 like the
FMGS language head), float16-rounded as stored, with the ties real scenes have: densification clones
sit at nearly the same point, so some rows are exact copies of others and some differ by one float16 step.

Query sets (each [n,D] unit float32):
  near     a scene embedding plus a little noise (best cosine ~0.99): near-duplicate queries
  typical  a scene embedding plus 0.6 noise (best cosine ~0.85): the old benchmark's queries
  clip     cosine t in [0.2, 0.35] with one scene embedding, the rest orthogonal to it: CLIP text-to-image
  absent   random directions (best cosine ~0.1-0.2): objects that are not in the scene
  ties     a duplicated row's own embedding: its copies tie exactly at the top
"""

from __future__ import annotations

import torch

from fmgs.vecmath import safe_normalize

QUERY_SETS = ("near", "typical", "clip", "absent", "ties")


def scene_embeddings(
    num: int,
    dim: int,
    seed: int = 0,
    copies: float = 0.03,
    means: torch.Tensor | None = None,
    dtype: torch.dtype = torch.float32,
) -> tuple[torch.Tensor, torch.Tensor]:
    """[num,dim] embeddings holding float16 values (stored as ``dtype``: float16 halves a 10M scene's
    memory), and [c] int64 rows that are copies.

    ``means`` [num,3] places the Gaussians (default: uniform in a unit cube); a fraction ``copies`` of
    the rows repeat another row exactly (half of them) or to within one float16 step (the other half).
    """
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(num, 3, generator=g) if means is None else means.float()
    lo, hi = x.min(0).values, x.max(0).values
    B = torch.randn(3, 32, generator=g) * torch.linspace(1, 12, 32)
    W1, b1 = torch.randn(64, 256, generator=g) / 8, torch.randn(256, generator=g) * 0.1
    W2, b2 = torch.randn(256, dim, generator=g) / 16, torch.randn(dim, generator=g) * 0.3
    out = torch.empty(num, dim, dtype=dtype)
    for s in range(0, num, 65536):
        p = (x[s : s + 65536] - lo) / (hi - lo).clamp_min(1e-9) @ B
        h = torch.relu(torch.cat([p.sin(), p.cos()], 1) @ W1 + b1)
        out[s : s + 65536] = safe_normalize(h @ W2 + b2).half().to(dtype)
    c = int(num * copies)
    dst = torch.randperm(num, generator=g)[:c]
    src = torch.randint(0, num, (c,), generator=g)
    out[dst] = out[src]
    near = dst[c // 2 :]
    col = torch.randint(0, dim, (len(near),), generator=g)
    h = out[near, col].half()
    out[near, col] = torch.nextafter(h, torch.full_like(h, 1.0)).to(dtype)  # one float16 step
    return out, dst.sort().values


def query_sets(emb: torch.Tensor, copies: torch.Tensor, n: int, seed: int = 1) -> dict[str, torch.Tensor]:
    """The query sets of the module docstring, n queries each, for scene embeddings emb [M,D]."""
    g = torch.Generator().manual_seed(seed)
    M, D = emb.shape

    def rows(k: int) -> torch.Tensor:
        return torch.randint(0, M, (k,), generator=g)

    def noise(k: int) -> torch.Tensor:
        return safe_normalize(torch.randn(k, D, generator=g))

    f = emb[rows(n)].float()
    u = noise(n)
    u = safe_normalize(u - (u * f).sum(1, keepdim=True) * f / (f * f).sum(1, keepdim=True))
    t = 0.2 + 0.15 * torch.rand(n, 1, generator=g)
    sets = {
        "near": safe_normalize(emb[rows(n)].float() + 0.05 * noise(n)),
        "typical": safe_normalize(emb[rows(n)].float() + 0.6 * noise(n)),
        "clip": safe_normalize(t * safe_normalize(f) + (1 - t * t).sqrt() * u),
        "absent": noise(n),
    }
    tie_rows = copies[torch.randint(0, max(1, len(copies)), (n,), generator=g)] if len(copies) else rows(n)
    sets["ties"] = safe_normalize(emb[tie_rows].float())
    return sets
