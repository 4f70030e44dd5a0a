"""CUDA backend through gsplat (``pip install 'fmgs[cuda]'``), loaded only when used.

gsplat implements the same EWA splatting with three documented differences from RasterConfig's rule:
alpha is clamped to 0.999 (not ``alpha_max``), a pixel stops when T <= 1e-4 (not < 1e-4), and all
geometry is float32 with fast math. Its images therefore agree with the reference to float32
accuracy except where those rules bite (saturated pixels); tests/render/test_cuda_gsplat.py measures this.
Per-pixel contribution statistics are not available from gsplat (n_contrib, weight_sum are None),
and radii are its opacity-aware per-axis extents (max of x and y), not 3-sigma radii.
"""

from __future__ import annotations

import torch

from fmgs.cameras import Camera
from fmgs.errors import BackendUnavailableError
from fmgs.render.types import RasterConfig, RenderOutput

# Channels gsplat blends per pass (it loops over chunks of this many). Measured on an H100
# (benchmarks/results/GPU.md, part "chunks"): a 899-channel garden render takes 38 ms in passes of 513,
# 20 ms in passes of 32; and gsplat 1.5.3's backward crashes the process (SIGSEGV) with 513-channel passes.
CHANNEL_CHUNK = 32


def load_gsplat():
    """Import gsplat.rasterization or raise BackendUnavailableError saying what is missing."""
    if not torch.cuda.is_available():
        raise BackendUnavailableError("the cuda backend needs a CUDA device; none is visible to torch")
    try:
        from gsplat import rasterization
    except ImportError as e:
        raise BackendUnavailableError(f"the cuda backend needs gsplat ({e}); pip install 'fmgs[cuda]'") from e
    return rasterization


def rasterize_gsplat(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    camera: Camera,
    background: torch.Tensor | None = None,
    config: RasterConfig = RasterConfig(),
) -> RenderOutput:
    """Same contract as fmgs.render.rasterize; CUDA tensors; differentiable through gsplat."""
    rasterization = load_gsplat()
    if not features.is_cuda:
        raise BackendUnavailableError("the cuda backend needs CUDA tensors; move the inputs to a CUDA device")
    dev, dt = features.device, features.dtype
    f32 = torch.float32
    D = features.shape[1]
    colors, alphas, meta = rasterization(
        means.to(f32),
        quats.to(f32),
        scales.to(f32),
        opacities.to(f32),
        features.to(f32),
        camera.viewmat.to(dev, f32)[None],
        camera.K.to(dev, f32)[None],
        camera.width,
        camera.height,
        near_plane=camera.near,
        far_plane=camera.far,
        eps2d=config.eps2d,
        packed=False,
        tile_size=config.tile_size,
        render_mode="RGB+ED",
        rasterize_mode="classic",
        backgrounds=None if background is None else background.to(dev, f32)[None],
        channel_chunk=min(D + 1, CHANNEL_CHUNK),
    )
    radii_xy = meta["radii"][0]
    visible = (radii_xy > 0).all(-1)
    means2d = meta["means2d"][0]
    if meta["means2d"].requires_grad:
        # The image depends on gsplat's [1,N,2] tensor, not on this [N,2] view of it, so autograd never
        # reaches the view: hand its gradient over (training reads out.means2d.grad for densification).
        def _to_view(grad: torch.Tensor) -> None:
            means2d.grad = grad[0]

        meta["means2d"].register_hook(_to_view)
    return RenderOutput(
        image=colors[0, ..., :D].to(dt),
        alpha=alphas[0, ..., 0].to(dt),
        depth=colors[0, ..., D].to(dt),
        radii=torch.where(visible, radii_xy.amax(-1), 0).to(torch.int32),
        means2d=means2d,
        visible=visible,
        n_contrib=None,
        weight_sum=None,
    )
