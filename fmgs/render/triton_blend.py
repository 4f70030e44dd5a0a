"""Wide-channel forward blending in one pass (Triton): the ``triton`` backend, inference only.

gsplat blends in passes of ``CHANNEL_CHUNK`` channels and evaluates every Gaussian's alpha again for each
pass, so an 899-channel render (CLIP + DINO + RGB) costs 29 passes over the geometry. Here the geometry is
evaluated once per pixel block and batch of Gaussians, and the batch's blending weights [pixels, k] meet
the features [k, channels] in a matrix product (``tl.dot``), so adding channels adds only that product.

The rule is RasterConfig's, exactly as ``reference.py`` applies it (gsplat's differs in three places,
cuda_gsplat.py): the projection is projection.py's float64 arithmetic in one launch (``project_triton``),
the binning is binning.py's; alpha and the transmittance are float64 in the kernel (``GEOM64``) or alpha
float32 from tile-relative float32 offsets; the weights meet the features in float32 (``PRECISION``:
"ieee" float32 FMAs or "tf32x3", three TF32 tensor-core products that keep float32 accuracy).

Without a GPU the same kernel runs in Triton's interpreter on CPU tensors (``TRITON_INTERPRET=1``; slow:
for tests only).
"""

from __future__ import annotations

import math
from functools import cache
from typing import NamedTuple

import torch

from fmgs.cameras import Camera
from fmgs.errors import BackendUnavailableError
from fmgs.render.binning import bin_tiles
from fmgs.render.types import Projection, RasterConfig, RenderOutput


class BlendTuning(NamedTuple):
    """Launch parameters of the kernel (they change speed, not the rule)."""

    block_pixels: int = 256
    """Pixels per program: a whole 16x16 tile, or a part of it (power of two)."""
    block_gaussians: int = 16
    """Gaussians per step of a tile's list (power of two, at least 16 for tl.dot)."""
    block_channels: int = 64
    """Channels per program (power of two, at least 16)."""
    geom64: bool = True
    """Alpha in float64 (the reference's precision) rather than float32 from tile-relative offsets."""
    precision: str = "tf32x3"
    """tl.dot input precision for weights x features: "ieee" or "tf32x3" (both float32-accurate)."""
    num_warps: int = 8
    """Warps per program."""
    stages: int = 2
    """Pipeline stages of the weights-once second pass's loop."""
    weights_once: int = 3
    """With at least this many blocks of channels (0: never), evaluate the weights once per tile
    (tile_weights, into a buffer no larger than the image) and multiply them by every block of channels
    (blend_weights), instead of evaluating them again in every block's program."""


TUNING = BlendTuning(block_pixels=64, num_warps=4)
"""The launch parameters ``rasterize_triton`` uses: the fastest of SWEEP on an H200 (GPU.md, part "paper")."""

SWEEP: dict[str, BlendTuning] = {
    "default": TUNING,
    "single_pass": BlendTuning(block_pixels=64, num_warps=4, weights_once=0),
    "once_p64c128k32": BlendTuning(64, 32, 128, num_warps=4, stages=3),
    "once_p256c64k32": BlendTuning(256, 32, 64, num_warps=8, stages=3),
    "once_p256c64w8": BlendTuning(),
    "geom32": BlendTuning(block_pixels=64, num_warps=4, geom64=False),
    "ieee": BlendTuning(block_pixels=64, num_warps=4, precision="ieee"),
    "single_pass_geom32_ieee": BlendTuning(64, num_warps=4, geom64=False, precision="ieee", weights_once=0),
}
"""Launches benchmarks/gpu_parts.py times against each other (tests/cuda holds each to the reference)."""


@cache
def _kernel(cpu: bool):
    """The jitted kernel; on CPU tensors it needs Triton's interpreter (TRITON_INTERPRET=1 at start)."""
    try:
        import triton

        from fmgs.render import triton_kernels
    except ImportError as e:
        raise BackendUnavailableError(f"the triton backend needs Triton ({e}); pip install triton") from e
    if cpu and not triton.knobs.runtime.interpret:
        raise BackendUnavailableError(
            "the triton backend runs on CUDA tensors; CPU tensors need Triton's interpreter "
            "(TRITON_INTERPRET=1 set before triton is imported)"
        )
    return triton_kernels


def project_triton(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    camera: Camera,
    config: RasterConfig,
) -> Projection:
    """projection.project in one kernel launch (its twin: the same float64 operations, tested against it):
    means [N,3], quats [N,4], scales [N,3], opacities [N] on one device -> Projection (float64)."""
    dev = means.device
    kernels = _kernel(dev.type == "cpu")
    N = means.shape[0]
    f64 = torch.float64
    V, K = camera.viewmat, camera.K
    cam = torch.tensor(
        [*V[:3, :3].reshape(-1).tolist(), *V[:3, 3].tolist(), float(K[0, 0]), float(K[1, 1]),
         float(K[0, 2]), float(K[1, 2]), camera.near, camera.far, config.eps2d, config.fov_clip,
         config.alpha_min],
        dtype=f64, device=dev,
    )  # fmt: skip
    means2d = torch.empty(N, 2, dtype=f64, device=dev)
    depths = torch.empty(N, dtype=f64, device=dev)
    conics = torch.empty(N, 3, dtype=f64, device=dev)
    opac = torch.empty(N, dtype=f64, device=dev)
    radii = torch.empty(N, dtype=torch.int32, device=dev)
    bbox = torch.empty(N, 4, dtype=torch.int64, device=dev)
    vis = torch.empty(N, dtype=torch.int8, device=dev)
    if N:
        block = 256
        kernels.project_gaussians[(-(-N // block),)](
            means.contiguous(), quats.contiguous(), scales.contiguous(), opacities.contiguous(), cam,
            means2d, depths, conics, opac, radii, bbox, vis, N, camera.width, camera.height, BLOCK=block,
        )  # fmt: skip
    return Projection(means2d, depths, conics, opac, radii, bbox, vis.bool())


def _pow2(n: int) -> int:
    return 1 << max(0, math.ceil(math.log2(max(n, 1))))


@torch.no_grad()
def rasterize_triton(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    camera: Camera,
    background: torch.Tensor | None = None,
    config: RasterConfig = RasterConfig(),
    tuning: BlendTuning | None = None,
) -> RenderOutput:
    """Same contract as fmgs.render.rasterize, without gradients: CUDA tensors (or CPU tensors through
    Triton's interpreter). Features [N,D] float32, float16 or bfloat16; the image comes back in their dtype.
    n_contrib and weight_sum are None."""
    tuning = tuning or TUNING
    dev, dt = features.device, features.dtype
    if dev.type not in ("cuda", "cpu"):
        raise BackendUnavailableError(f"the triton backend runs on CUDA devices, not {dev.type}")
    kernels = _kernel(dev.type == "cpu")
    N, D = features.shape
    W, H, T = camera.width, camera.height, config.tile_size
    proj = project_triton(means, quats, scales, opacities, camera, config)
    bins = bin_tiles(proj, W, H, T)
    n_tiles = bins.tiles_x * bins.tiles_y
    BP = min(_pow2(tuning.block_pixels), _pow2(T * T))
    sub = -(-(T * T) // BP)
    CB = max(16, min(_pow2(tuning.block_channels), _pow2(D)))
    BK = max(16, _pow2(tuning.block_gaussians))
    feats = features if features.dtype in (torch.float32, torch.float16, torch.bfloat16) else features.float()
    feats = feats.contiguous()
    launch = N > 0 and len(bins.gauss_ids) > 0 and H > 0 and W > 0
    # The kernel writes every pixel (all tiles are launched); without a launch nothing is blended, T = 1.
    out = (torch.empty if launch else torch.zeros)(H, W, D, dtype=torch.float32, device=dev)
    aux = torch.empty(3, H, W, dtype=torch.float64, device=dev)
    if not launch:
        aux[0].zero_(), aux[1].zero_(), aux[2].fill_(1.0)
    else:
        f64 = torch.float64
        rule = [config.alpha_min, config.alpha_max, config.transmittance_min]
        means2d, conics, opac, depths = (
            t.to(f64).contiguous() for t in (proj.means2d, proj.conics, proj.opacities, proj.depths)
        )
        grid = (n_tiles * sub, -(-D // CB))
        warps = {} if dev.type == "cpu" else {"num_warps": tuning.num_warps}
        rule_t = torch.tensor(rule, dtype=f64, device=dev)
        interpret = dev.type == "cpu"
        once = tuning.weights_once > 0 and grid[1] >= tuning.weights_once
        if once:
            extent = torch.empty(n_tiles, dtype=torch.int64, device=dev)
            kernels.tile_extents[(n_tiles,)](
                bins.gauss_ids, bins.offsets, means2d, conics, opac, extent, W, H, bins.tiles_x, rule_t,
                TILE=T, BP=_pow2(T * T), BK=BK, GEOM64=tuning.geom64, **warps,
            )  # fmt: skip
        if once:
            rows = (extent + BK - 1) // BK * BK
            size = rows * (T * T)
            total = int(size.sum())
            # The buffer is bounded by the image it makes (else the single pass, which needs none).
            once = total <= H * W * D
        if once:
            wbase = torch.cumsum(size, 0) - size
            weights = torch.empty(max(total, 1), dtype=torch.float32, device=dev)
            kernels.tile_weights[(n_tiles * sub,)](
                bins.gauss_ids, bins.offsets, extent, wbase, means2d, conics, opac, depths, weights, aux,
                W, H, bins.tiles_x, rule_t, TILE=T, SUB=sub, BP=BP, BK=BK, GEOM64=tuning.geom64, **warps,
            )  # fmt: skip
            kernels.blend_weights[grid](
                bins.gauss_ids, bins.offsets, extent, wbase, weights, feats, out, W, H, D, feats.stride(0),
                bins.tiles_x, TILE=T, SUB=sub, BP=BP, BK=BK, CB=CB, PRECISION=tuning.precision,
                STAGES=tuning.stages, INTERPRET=interpret, **warps,
            )  # fmt: skip
        else:
            kernels.blend_tiles[grid](
                bins.gauss_ids,
                bins.offsets,
                means2d,
                conics,
                opac,
                depths,
                feats,
                out,
                aux,
                W,
                H,
                D,
                feats.stride(0),
                bins.tiles_x,
                rule_t,
                TILE=T,
                SUB=sub,
                BP=BP,
                BK=BK,
                CB=CB,
                GEOM64=tuning.geom64,
                PRECISION=tuning.precision,
                **warps,
            )
    wsum, zsum, t_final = aux[0], aux[1], aux[2]
    image = out
    if background is not None:
        image = image + t_final[..., None].float() * background.to(device=dev, dtype=torch.float32)
    depth = zsum / torch.where(wsum > 0, wsum, torch.ones_like(wsum))
    return RenderOutput(
        image=image.to(dt),
        alpha=wsum.to(dt),
        depth=depth.to(dt),
        radii=proj.radii,
        means2d=proj.means2d,
        visible=proj.visible,
        n_contrib=None,
        weight_sum=None,
    )
