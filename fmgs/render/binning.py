"""Tile binning: which Gaussians touch which tile, in front-to-back order."""

from __future__ import annotations

from typing import NamedTuple

import torch

from fmgs.render.types import Projection


class TileBins(NamedTuple):
    """Per-tile Gaussian lists, concatenated: tile t owns gauss_ids[offsets[t]:offsets[t+1]]."""

    gauss_ids: torch.Tensor
    """[P] int64 Gaussian indices, front to back within each tile."""
    offsets: torch.Tensor
    """[T+1] int64 start of each tile's list."""
    tiles_x: int
    """Number of tile columns."""
    tiles_y: int
    """Number of tile rows."""


def depth_order(proj: Projection) -> torch.Tensor:
    """Indices of the visible Gaussians sorted front to back (stable: ties keep index order)."""
    idx = torch.nonzero(proj.visible, as_tuple=False).squeeze(1)
    order = torch.sort(proj.depths.detach()[idx], stable=True).indices
    return idx[order]


def bin_tiles(proj: Projection, width: int, height: int, tile: int) -> TileBins:
    """Bin visible Gaussians into tile x tile pixel tiles using their conservative boxes."""
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    ids = depth_order(proj)
    dev = ids.device
    box = proj.bbox[ids] // tile  # tile-space inclusive box
    nx = box[:, 2] - box[:, 0] + 1
    ny = box[:, 3] - box[:, 1] + 1
    count = nx * ny
    total = int(count.sum())
    # output_size: the total is known, so neither expansion waits on the device for it again
    owner = torch.repeat_interleave(torch.arange(len(ids), device=dev), count, output_size=total)
    first = torch.repeat_interleave(torch.cumsum(count, 0) - count, count, output_size=total)
    local = torch.arange(total, device=dev) - first
    tx = box[owner, 0] + local % nx[owner]
    ty = box[owner, 1] + local // nx[owner]
    tile_id = ty * tiles_x + tx
    # A stable sort by tile keeps the front-to-back order inside each tile.
    perm = torch.sort(tile_id, stable=True).indices
    gauss_ids = ids[owner[perm]]
    counts = torch.bincount(tile_id, minlength=tiles_x * tiles_y)
    offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.int64, device=dev)
    offsets[1:] = torch.cumsum(counts, 0)
    return TileBins(gauss_ids, offsets, tiles_x, tiles_y)
