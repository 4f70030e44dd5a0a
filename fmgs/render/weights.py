"""Blending weights of frozen geometry as a sparse matrix: render any features by one sparse product.

Blending is linear in the features: image(p) = sum_k w_k(p) f_k. Once geometry is frozen (the feature
field stage), the weights w_k(p) of a view never change, so they are computed once with the reference
rasteriser's own blending code and every later render of that view is ``W @ f`` — exact to the
rounding of the product, with gradients ``W^T @ g``. Only the Gaussians that reach a pixel of the view
are kept as columns, so the features need only be evaluated for those.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from fmgs.cameras import Camera
from fmgs.render.binning import bin_tiles
from fmgs.render.projection import project
from fmgs.render.reference import blend_chunk, tile_batches
from fmgs.render.types import RasterConfig
from fmgs.sparse import SparseMatrix

GPU_CHUNK_ELEMS = 1 << 24
"""Pixel x Gaussian elements per chunk of ``view_weights`` on a GPU: 16x the CPU default, so a view takes
few launches (each chunk's float64 temporaries stay near 1 GiB)."""


def weights_config(device: torch.device | str) -> RasterConfig:
    """The default rule with a chunk size suited to ``device`` for ``view_weights`` (the CPU default
    bounds host memory; on a GPU larger chunks save kernel launches and host syncs)."""
    if torch.device(device).type == "cpu":
        return RasterConfig()
    return RasterConfig(chunk_elems=GPU_CHUNK_ELEMS)


class ViewWeights(NamedTuple):
    """Blending weights of one view: ``image = (W @ features[gaussians]).reshape(height, width, D)``."""

    matrix: SparseMatrix
    """[H*W, M] float32 (or float64) weights; row = pixel (row-major), column = local index."""
    gaussians: torch.Tensor
    """[M] int64 global indices of the Gaussians with a non-zero weight somewhere in the view."""
    height: int
    """Image height."""
    width: int
    """Image width."""

    def render(self, features: torch.Tensor) -> torch.Tensor:
        """[H,W,D] blend of features [M,D] (already gathered to ``gaussians``), differentiable in them."""
        return self.matrix.matmul(features).reshape(self.height, self.width, -1)

    def to(self, device: torch.device | str) -> ViewWeights:
        return ViewWeights(self.matrix.to(device), self.gaussians.to(device), self.height, self.width)


@torch.no_grad()
def view_weights(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    camera: Camera,
    config: RasterConfig | None = None,
    dtype: torch.dtype = torch.float32,
) -> ViewWeights:
    """Blending weights for ``camera`` (means [N,3], quats [N,4] wxyz, scales [N,3], opacities [N]).

    Uses the reference rasteriser's chunked blend, so the weights are the ones it renders with.
    """
    config = config or RasterConfig()
    N = means.shape[0]
    W, H, T = camera.width, camera.height, config.tile_size
    dev = means.device
    proj = project(means, quats, scales, opacities, camera, config)
    bins = bin_tiles(proj, W, H, T)
    P = T * T
    ly, lx = torch.meshgrid(torch.arange(T, device=dev), torch.arange(T, device=dev), indexing="ij")
    lx, ly = lx.reshape(1, P), ly.reshape(1, P)
    counts = (bins.offsets[1:] - bins.offsets[:-1]).tolist()
    offsets = bins.offsets.tolist()
    dummy = torch.zeros(N, 1, dtype=torch.float64, device=dev)
    rows, cols, vals = [], [], []
    for tiles, kmax in tile_batches(counts, P, 1, config.chunk_elems):
        tb = torch.tensor(tiles, device=dev)
        B = len(tiles)
        k = torch.arange(kmax, device=dev)
        starts = torch.tensor([offsets[t] for t in tiles], device=dev)
        lens = torch.tensor([counts[t] for t in tiles], device=dev)
        valid = k[None, :] < lens[:, None]
        flat = (starts[:, None] + k[None, :]).clamp_max(max(len(bins.gauss_ids) - 1, 0))
        gid = torch.where(valid, bins.gauss_ids[flat], 0)
        kc = max(1, config.chunk_elems // (B * P))
        Tcar = torch.ones(B, P, dtype=torch.float64, device=dev)
        done = torch.zeros(B, P, dtype=torch.bool, device=dev)
        px = (tb % bins.tiles_x * T)[:, None] + lx
        py = (tb // bins.tiles_x * T)[:, None] + ly
        ok_pix = (px < W) & (py < H)
        pix_b = (torch.stack([px, py], -1).to(torch.float64) + 0.5)[:, :, None, :]
        pixel = py * W + px  # [B,P]
        for k0 in range(0, kmax, kc):
            if bool(done[ok_pix].all()):
                break
            g = gid[:, k0 : k0 + kc]
            gv = valid[:, k0 : k0 + kc]
            args = (pix_b, g, gv, proj.means2d, proj.conics, proj.opacities, proj.depths, dummy, Tcar, done)
            _, _, _, Tcar, stop, w = blend_chunk(*args, config)
            done = done | stop
            keep = (w > 0) & ok_pix[..., None]  # [B,P,k]
            b, p, j = torch.nonzero(keep, as_tuple=True)
            rows.append(pixel[b, p])
            cols.append(g[b, j])
            vals.append(w[b, p, j])
    if rows:
        r, c, v = torch.cat(rows), torch.cat(cols), torch.cat(vals)
    else:
        r = c = torch.zeros(0, dtype=torch.int64, device=dev)
        v = torch.zeros(0, dtype=torch.float64, device=dev)
    gauss, local = torch.unique(c, return_inverse=True)
    return ViewWeights(SparseMatrix.from_coo(r, local, v.to(dtype), (H * W, len(gauss))), gauss, H, W)
