"""Differentiable CPU path: the reference's projection and binning (PyTorch, autograd) with blending
forward and backward in numba kernels (``cpu_grad_kernels.py``).

The exact twin is ``rasterize_reference``: the same rule in float64, so outputs and gradients agree to
rounding (tests/render/test_cpu_grad.py). Memory: the backward pass holds one gradient row of 7 + D
float64 values per (tile, Gaussian) pair of the binning, so wide features (hundreds of channels) are
better served by the reference path, which ``backend="auto"`` picks for them.
"""

from __future__ import annotations

import numpy as np
import torch

from fmgs.cameras import Camera
from fmgs.render.binning import bin_tiles
from fmgs.render.cpu_fast import costliest_tiles_first, f64_array, load_kernels
from fmgs.render.projection import project
from fmgs.render.types import RasterConfig, RenderOutput

# auto uses this path for gradients up to this many channels (RGB training); wider goes to the reference
MAX_AUTO_CHANNELS = 32


class _Blend(torch.autograd.Function):
    """(means2d [N,2], conics [N,3], opacities [N], depths [N], features [N,D], all float64) ->
    (feature sum [H,W,D], weight sum [H,W], depth sum [H,W], final transmittance [H,W]) and the
    non-differentiable statistics n_contrib [N] int32, weight_sum [N] float64."""

    @staticmethod
    def forward(ctx, means2d, conics, opac, depths, features, bins, bbox, camera, config):
        k = load_kernels("cpu_grad_kernels")
        import numba

        N, D = features.shape
        W, H, T = camera.width, camera.height, config.tile_size
        ids = np.ascontiguousarray(bins.gauss_ids.numpy())
        offsets = np.ascontiguousarray(bins.offsets.numpy())
        tile_order = costliest_tiles_first(offsets)  # handed out one at a time
        arrays = [f64_array(x) for x in (means2d, conics, opac, depths)]
        box = np.ascontiguousarray(bbox.numpy())
        feats = f64_array(features)
        feat = np.zeros((H, W, D))
        wsum = np.zeros((H, W))
        zsum = np.zeros((H, W))
        t_img = np.ones((H, W))
        last = np.zeros((H, W), dtype=np.int64)
        pair_cnt = np.zeros(len(ids), dtype=np.int64)
        pair_w = np.zeros(len(ids))
        geo = (ids, offsets, tile_order, T, bins.tiles_x, W, H)
        with numba.parallel_chunksize(1):
            k.blend_forward(
                *geo, *arrays, box, feats, config.alpha_max, config.alpha_min, config.transmittance_min,
                feat, wsum, zsum, t_img, last, pair_cnt, pair_w,
            )  # fmt: skip
        ctx.saved = (geo, arrays, box, feats, t_img, last, config, N)
        n_contrib = torch.from_numpy(np.bincount(ids, weights=pair_cnt, minlength=N).astype(np.int32))
        weight_sum = torch.from_numpy(np.bincount(ids, weights=pair_w, minlength=N))
        ctx.mark_non_differentiable(n_contrib, weight_sum)
        t = torch.from_numpy
        return t(feat), t(wsum), t(zsum), t(t_img), n_contrib, weight_sum

    @staticmethod
    def backward(ctx, g_feat, g_wsum, g_zsum, g_t, _g_cnt, _g_w):
        k = load_kernels("cpu_grad_kernels")
        import numba

        geo, arrays, box, feats, t_img, last, config, N = ctx.saved
        ids = geo[0]
        (H, W), D = t_img.shape, feats.shape[1]

        def grad(x, shape):
            return np.zeros(shape) if x is None else np.ascontiguousarray(x.to(torch.float64).numpy())

        E = len(ids)
        rows = {
            "means2d": np.zeros((E, 2)),
            "conics": np.zeros((E, 3)),
            "opac": np.zeros(E),
            "depths": np.zeros(E),
            "features": np.zeros((E, D)),
        }
        with numba.parallel_chunksize(1):
            k.blend_backward(
                *geo, *arrays, box, feats, config.alpha_max, config.alpha_min, t_img, last,
                grad(g_feat, (H, W, D)), grad(g_wsum, (H, W)), grad(g_zsum, (H, W)), grad(g_t, (H, W)),
                *rows.values(),
            )  # fmt: skip
        idx = torch.from_numpy(ids)
        out = []
        for name in rows:
            r = torch.from_numpy(rows[name])
            out.append(torch.zeros((N, *r.shape[1:]), dtype=torch.float64).index_add_(0, idx, r))
        return (*out, None, None, None, None)


def rasterize_cpu_grad(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    camera: Camera,
    background: torch.Tensor | None = None,
    config: RasterConfig = RasterConfig(),
) -> RenderOutput:
    """Same contract as fmgs.render.rasterize; CPU tensors, differentiable in every input."""
    fdt = features.dtype
    proj = project(means, quats, scales, opacities, camera, config)
    bins = bin_tiles(proj, camera.width, camera.height, config.tile_size)
    feat, wsum, zsum, t_fin, n_contrib, weight_sum = _Blend.apply(
        proj.means2d, proj.conics, proj.opacities, proj.depths, features.to(torch.float64),
        bins, proj.bbox, camera, config,
    )  # fmt: skip
    image = feat.to(fdt)
    if background is not None:
        image = image + t_fin[..., None].to(fdt) * background.to(dtype=fdt)
    depth = zsum / torch.where(wsum > 0, wsum, torch.ones_like(wsum))
    return RenderOutput(
        image=image,
        alpha=wsum.to(fdt),
        depth=depth.to(fdt),
        radii=proj.radii,
        means2d=proj.means2d,
        visible=proj.visible,
        n_contrib=n_contrib,
        weight_sum=weight_sum,
    )
