"""One rasteriser interface over three backends.

- ``reference``: pure PyTorch, differentiable, any device, float32/float64 (``reference.py``);
- ``cpu``: compiled numba kernels, loaded lazily: without gradients the fast inference path
  (``cpu_fast.py``), with gradients numba blending forward and backward behind the reference's
  projection (``cpu_grad.py``);
- ``cuda``: gsplat on a CUDA device (``cuda_gsplat.py``), loaded lazily;
- ``triton``: a one-pass wide-channel forward kernel on a CUDA device with the reference's exact rule
  (``triton_blend.py``), no gradients, loaded lazily.

``backend="auto"`` picks, for CUDA tensors, ``triton`` when no gradient is needed (and Triton is installed)
and ``cuda`` otherwise; on the CPU, ``cpu`` when no gradient is needed or the features are narrow (RGB
training), else ``reference``.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from fmgs.cameras import Camera
from fmgs.checks import check_finite, check_shape, first_bad_row
from fmgs.errors import ValidationError
from fmgs.render.types import Projection, RasterConfig, RenderOutput

__all__ = [
    "BACKENDS", "Projection", "RasterConfig", "RenderOutput", "rasterize", "validate_inputs", "visible",
]  # fmt: skip

BACKENDS = ("auto", "reference", "cpu", "cuda", "triton")


def validate_inputs(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    background: torch.Tensor | None,
) -> None:
    """Raise ValidationError naming the field and first bad row of any malformed input."""
    n = means.shape[0] if means.ndim == 2 else -1
    check_shape("means", means, (n, 3))
    check_shape("quats", quats, (n, 4))
    check_shape("scales", scales, (n, 3))
    check_shape("opacities", opacities, (n,))
    check_shape("features", features, (n, None))
    if features.shape[1] < 1:
        raise ValidationError("features", "need at least one channel")
    for name, t in (
        ("means", means),
        ("quats", quats),
        ("scales", scales),
        ("opacities", opacities),
        ("features", features),
    ):
        check_finite(name, t)
    # Reductions first (no temporaries); the masks are built only to name the first bad row.
    if quats.numel() and bool(quats.abs().amax(1).min() == 0):
        raise ValidationError("quats", "zero quaternion", first_bad_row((quats == 0).all(1)))
    if scales.numel() and bool(scales.min() <= 0):
        raise ValidationError("scales", "must be positive (pass exp(log_scales))", first_bad_row(scales <= 0))
    if opacities.numel():
        lo, hi = torch.aminmax(opacities)
        if bool(lo < 0) or bool(hi > 1):
            bad = (opacities < 0) | (opacities > 1)
            raise ValidationError(
                "opacities", "must lie in [0, 1] (pass sigmoid(logits))", first_bad_row(bad)
            )
    if background is not None:
        check_shape("background", background, (features.shape[1],))
        check_finite("background", background)


@torch.no_grad()
def visible(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    camera: Camera,
    config: RasterConfig | None = None,
    backend: str = "auto",
) -> torch.Tensor:
    """[N] bool: the Gaussians ``rasterize`` can blend into a pixel of ``camera``'s image (in the depth
    range, opacity at least alpha_min, alpha box overlapping the image); the others contribute nothing,
    whatever their features. The cpu backend's own culling (its projection kernel) on CPU tensors, the
    float64 projection's conservative box elsewhere. Activated inputs, as for ``rasterize``."""
    config = config or RasterConfig()
    if means.device.type == "cpu" and backend in ("auto", "cpu"):
        from fmgs.render.cpu_fast import project_cpu

        return torch.from_numpy(project_cpu(means, quats, scales, opacities, camera, config)["visible"])
    from fmgs.render.projection import project

    return project(means, quats, scales, opacities, camera, config).visible.cpu()


def _have_triton() -> bool:
    import importlib.util

    return importlib.util.find_spec("triton") is not None


def _grad_channels() -> int:
    from fmgs.render.cpu_grad import MAX_AUTO_CHANNELS

    return MAX_AUTO_CHANNELS


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    camera: Camera,
    background: torch.Tensor | None = None,
    config: RasterConfig | None = None,
    backend: str = "auto",
    between_tiles: Callable[[], None] | None = None,
) -> RenderOutput:
    """Alpha-blend per-Gaussian features [N,D] into a [H,W,D] image for ``camera``.

    Inputs are activated: scales [N,3] positive (exp of log scales), opacities [N] in [0,1],
    quaternions [N,4] wxyz of any non-zero norm. All on one device. ``between_tiles`` is called between
    batches of tiles on the cpu backend (and once after the other backends): it may raise to stop a
    render whose answer is no longer wanted.
    """
    config = config or RasterConfig()
    validate_inputs(means, quats, scales, opacities, features, background)
    if backend not in BACKENDS:
        raise ValidationError("backend", f"unknown backend {backend!r}; choose one of {BACKENDS}")
    needs_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means, quats, scales, opacities, features)
    )
    if backend == "auto":
        if features.is_cuda:
            # Renders without gradients follow the reference's rule exactly (images agree with the CPU's);
            # training needs gsplat's backward.
            backend = "cuda" if needs_grad or not _have_triton() else "triton"
        elif features.device.type == "cpu" and (not needs_grad or features.shape[1] <= _grad_channels()):
            backend = "cpu"
        else:
            backend = "reference"
    if backend == "triton":
        if needs_grad:
            raise ValidationError("backend", "the triton backend renders without gradients; train with cuda")
        from fmgs.render.triton_blend import rasterize_triton

        out = rasterize_triton(means, quats, scales, opacities, features, camera, background, config)
        if between_tiles is not None:
            between_tiles()
        return out
    if backend == "reference":
        from fmgs.render.reference import rasterize_reference

        out = rasterize_reference(means, quats, scales, opacities, features, camera, background, config)
        if between_tiles is not None:
            between_tiles()
        return out
    if backend == "cpu":
        if needs_grad:
            from fmgs.render.cpu_grad import rasterize_cpu_grad

            return rasterize_cpu_grad(means, quats, scales, opacities, features, camera, background, config)
        from fmgs.render.cpu_fast import rasterize_cpu

        return rasterize_cpu(
            means, quats, scales, opacities, features, camera, background, config, between_tiles
        )
    from fmgs.render.cuda_gsplat import rasterize_gsplat

    out = rasterize_gsplat(means, quats, scales, opacities, features, camera, background, config)
    if between_tiles is not None:
        between_tiles()
    return out
