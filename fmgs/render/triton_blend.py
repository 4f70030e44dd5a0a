"""Wide-channel forward blending in one pass (Triton): the ``triton`` backend, inference only.

gsplat blends in passes of ``CHANNEL_CHUNK`` channels and evaluates every Gaussian's alpha again for each
pass, so an 899-channel render (CLIP + DINO + RGB) costs 29 passes over the geometry. Here the geometry is
evaluated once per pixel block and batch of Gaussians, and the batch's blending weights [pixels, k] meet
the features [k, channels] in a matrix product (``tl.dot``), so adding channels adds only that product.

The rule is RasterConfig's, exactly as ``reference.py`` applies it (gsplat's differs in three places,
cuda_gsplat.py): the projection and binning are the reference's own float64 torch code; alpha and the
transmittance are float64 in the kernel (``GEOM64``) or alpha float32 from tile-relative float32
offsets; the weights meet the features in float32 (``PRECISION``: "ieee" float32 FMAs or "tf32x3",
three TF32 tensor-core products that keep float32 accuracy).

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
from fmgs.render.projection import project
from fmgs.render.types import RasterConfig, RenderOutput


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
    pipelined: bool = False
    """Measure each tile's extent first (tile_extents), then blend in a software-pipelined ``for`` loop
    over it, instead of a ``while`` loop that stops when every pixel has terminated."""
    stages: int = 2
    """Pipeline stages of the ``for`` loop (with ``pipelined``)."""


TUNING = BlendTuning(block_pixels=64, num_warps=4)
"""The launch parameters ``rasterize_triton`` uses: the fastest of SWEEP on an H200 (benchmarks/results/GPU.md,
part "paper")."""

SWEEP: dict[str, BlendTuning] = {
    "default": BlendTuning(block_pixels=64, num_warps=4),
    "p256c64w8": BlendTuning(),
    "p256c32": BlendTuning(block_channels=32),
    "p128c32w4": BlendTuning(block_pixels=128, block_channels=32, num_warps=4),
    "geom32": BlendTuning(block_pixels=64, num_warps=4, geom64=False),
    "ieee": BlendTuning(block_pixels=64, num_warps=4, precision="ieee"),
    "geom32_ieee": BlendTuning(block_pixels=64, num_warps=4, geom64=False, precision="ieee"),
    "pipelined": BlendTuning(block_pixels=128, block_gaussians=32, block_channels=32, pipelined=True),
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
    proj = project(means, quats, scales, opacities, camera, config)
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
        means2d, conics, opac = (t.to(f64).contiguous() for t in (proj.means2d, proj.conics, proj.opacities))
        grid = (n_tiles * sub, -(-D // CB))
        warps = {} if dev.type == "cpu" else {"num_warps": tuning.num_warps}
        rule_t = torch.tensor(rule, dtype=f64, device=dev)
        extent = bins.offsets  # unread unless pipelined
        if tuning.pipelined:
            extent = torch.empty(n_tiles, dtype=torch.int64, device=dev)
            kernels.tile_extents[(n_tiles,)](
                bins.gauss_ids, bins.offsets, means2d, conics, opac, extent, W, H, bins.tiles_x, rule_t,
                TILE=T, BP=_pow2(T * T), BK=BK, GEOM64=tuning.geom64, **warps,
            )  # fmt: skip
        kernels.blend_tiles[grid](
            bins.gauss_ids,
            bins.offsets,
            extent,
            means2d,
            conics,
            opac,
            proj.depths.to(f64).contiguous(),
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
            PIPELINED=tuning.pipelined,
            STAGES=tuning.stages,
            INTERPRET=dev.type == "cpu",
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
