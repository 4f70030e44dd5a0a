"""Multi-resolution hash encoding (Instant-NGP style), pure PyTorch, any device.

Level l has resolution floor(min_res * b^l) with b = (max_res / min_res)^(1 / (levels - 1)). Its grid
vertices are indexed densely while (res + 1)^3 fits the table, and through the spatial hash
(x * 1) xor (y * 2654435761) xor (z * 805459861) mod T above that. A point's feature at a level is the
trilinear blend of its cell's 8 vertex entries; the levels are concatenated.

Sparse tables. The field is only ever trained at known points (the Gaussian means), so most table rows
never receive a gradient. ``HashGrid.compact(points)`` keeps only the rows those points touch: the
encoding at those points is identical to the full table's, and any other point reads untouched rows as
zero. Rows are addressed by their global index (level offset + dense or hashed index) through a sorted
key list, so a full grid is the special case of keys 0..total-1.

Fast paths: ``encode`` uses ``torch.nn.functional.embedding_bag`` (gather + weighted sum without
materialising the [N, L, 8, F] corner features); for fixed points ``interpolation_matrix`` and
``encode_matrix`` turn the interpolation into a CSR product. Reference twin: ``encode_reference``
(explicit gather and sum).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import nn

from fmgs.field.config import HashGridConfig
from fmgs.sparse import SparseMatrix

_PRIMES = (1, 2654435761, 805459861)
# The 8 cell corners as (dx, dy, dz) bits.
_CORNERS = torch.tensor([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype=torch.int64)


def scene_max_res(points: torch.Tensor, cfg: HashGridConfig) -> int:
    """Finest resolution the points can use: one cell per median nearest-neighbour spacing of points
    [N,3] (unit cube), clamped to [min_res, max_res]. Finer levels only separate Gaussians that are
    already apart, so the scene-adaptive option stops there."""
    from scipy.spatial import cKDTree

    p = points.detach().cpu().double().numpy()
    if len(p) < 2:
        return cfg.min_res
    d, _ = cKDTree(p).query(p, k=2)
    spacing = float(torch.tensor(d[:, 1]).median())
    if spacing <= 0:
        return cfg.max_res
    return int(min(cfg.max_res, max(cfg.min_res, math.ceil((1 - 1e-5) / spacing))))


class Corners(NamedTuple):
    """Where points read the table: global row indices and trilinear weights."""

    rows: torch.Tensor
    """[N, L, 8] int64 global row index of each cell corner."""
    weights: torch.Tensor
    """[N, L, 8] trilinear weights (dtype of the points; differentiable in them)."""


def corners(x: torch.Tensor, cfg: HashGridConfig) -> Corners:
    """Cell corners of points x [N,3] in the unit cube (values outside are clamped to it)."""
    dev = x.device
    res = torch.tensor(cfg.resolutions(), device=dev, dtype=torch.int64)  # [L]
    sizes = cfg.level_sizes()
    offsets = torch.tensor([0, *sizes[:-1]], device=dev, dtype=torch.int64).cumsum(0)  # [L]
    dense = torch.tensor([(r + 1) ** 3 <= (1 << cfg.log2_table) for r in cfg.resolutions()], device=dev)
    x = x.clamp(0.0, 1.0)
    pos = x[:, None, :] * res[None, :, None].to(x.dtype)  # [N,L,3]
    cell = pos.detach().floor().to(torch.int64)
    cell = torch.minimum(cell, (res - 1)[None, :, None])  # x == 1 falls in the last cell
    frac = pos - cell.to(x.dtype)  # [N,L,3]
    c = cell[:, :, None, :] + _CORNERS.to(dev)[None, None]  # [N,L,8,3]
    stride = (res + 1)[None, :, None]
    dense_idx = c[..., 0] + c[..., 1] * stride + c[..., 2] * stride * stride
    hashed = (c[..., 0] * _PRIMES[0]) ^ (c[..., 1] * _PRIMES[1]) ^ (c[..., 2] * _PRIMES[2])
    hashed = hashed & ((1 << cfg.log2_table) - 1)
    idx = torch.where(dense[None, :, None], dense_idx, hashed) + offsets[None, :, None]
    bits = _CORNERS.to(dev).to(x.dtype)  # [8,3]
    f = frac[:, :, None, :]  # [N,L,1,3]
    w = torch.where(bits.bool(), f, 1.0 - f).prod(-1)  # [N,L,8]
    return Corners(idx, w)


class HashGrid(nn.Module):
    """The encoding's table, full or compacted to the rows some points touch."""

    def __init__(
        self,
        cfg: HashGridConfig,
        keys: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        """keys [M] sorted int64 global rows held (None: every row of the full grid)."""
        super().__init__()
        self.cfg = cfg
        total = sum(cfg.level_sizes())
        self.full = keys is None
        if keys is None:
            keys = torch.arange(total, dtype=torch.int64)
        if keys.ndim != 1 or (len(keys) > 1 and bool((keys[1:] <= keys[:-1]).any())):
            raise ValueError("keys must be a 1-D strictly increasing list of table rows")
        if len(keys) and (int(keys[0]) < 0 or int(keys[-1]) >= total):
            raise ValueError(f"keys must lie in [0, {total})")
        self.register_buffer("keys", keys)
        table = torch.rand(len(keys), cfg.features, generator=generator, dtype=dtype)
        self.table = nn.Parameter((table * 2 - 1) * cfg.init_scale)

    @classmethod
    def compact(
        cls,
        cfg: HashGridConfig,
        points: torch.Tensor,
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float32,
    ) -> HashGrid:
        """A grid holding only the rows touched by points [N,3] (unit cube)."""
        rows = corners(points.detach(), cfg).rows
        return cls(cfg, torch.unique(rows.reshape(-1)).cpu(), generator, dtype)

    def local_rows(self, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Global rows [...] -> (table rows [...], held [...] bool); rows not held map to 0."""
        if self.full:
            return rows, torch.ones_like(rows, dtype=torch.bool)
        if len(self.keys) == 0:
            return torch.zeros_like(rows), torch.zeros_like(rows, dtype=torch.bool)
        pos = torch.searchsorted(self.keys, rows).clamp_max(len(self.keys) - 1)
        held = self.keys[pos] == rows
        return torch.where(held, pos, 0), held

    def lookup(self, x: torch.Tensor) -> Corners:
        """Table rows and weights for points x [N,3]; weights of rows not held are zero."""
        c = corners(x, self.cfg)
        rows, held = self.local_rows(c.rows)
        return Corners(rows, torch.where(held, c.weights, torch.zeros_like(c.weights)))

    def encode(self, look: Corners) -> torch.Tensor:
        """[N, L*F] encoding from a lookup (fast path: embedding_bag)."""
        N, L, _ = look.rows.shape
        w = look.weights.to(self.table.dtype)
        out = nn.functional.embedding_bag(
            look.rows.reshape(N * L, 8), self.table, per_sample_weights=w.reshape(N * L, 8), mode="sum"
        )
        return out.reshape(N, L * self.cfg.features)

    def encode_reference(self, look: Corners) -> torch.Tensor:
        """Reference twin of ``encode``: explicit gather of the 8 corners and weighted sum."""
        N = look.rows.shape[0]
        feats = self.table[look.rows]  # [N,L,8,F]
        return (look.weights.to(self.table.dtype)[..., None] * feats).sum(2).reshape(N, -1)

    def interpolation_matrix(self, look: Corners) -> SparseMatrix:
        """[N*L, M] sparse matrix A with encode(look) == (A @ table).reshape(N, L*F).

        For fixed points (the Gaussian means while the field trains): the lookup is done once and each
        step is a CSR product whose backward is the precomputed transpose product (no sorting).
        """
        N, L, _ = look.rows.shape
        r = torch.arange(N * L, device=look.rows.device).repeat_interleave(8)
        w = look.weights.detach().to(self.table.dtype).reshape(-1)
        return SparseMatrix.from_coo(r, look.rows.reshape(-1), w, (N * L, len(self.keys)))

    def encode_matrix(self, a: SparseMatrix) -> torch.Tensor:
        """[N, L*F] encoding of the points behind ``interpolation_matrix``."""
        return a.matmul(self.table).reshape(-1, self.cfg.out_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """[N, L*F] encoding of points x [N,3] in the unit cube."""
        return self.encode(self.lookup(x))
