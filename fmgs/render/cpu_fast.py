"""CPU fast path: numba kernels for inference without gradients.

Matches the reference backend (same rule, float64 geometry and weights) and adds per-pixel early
termination, a power prefilter that skips exp() where alpha is surely below alpha_min, and a table-driven
exp (2 ulp). Formulas differ from the reference only in rounding order, so discrete decisions can differ
only for values within ~1e-15 (relative) of a threshold. Threads: numba's pool
(NUMBA_NUM_THREADS, default all cores); tiles are handed out one at a time, costliest first.
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Callable

import numpy as np
import torch

from fmgs.cameras import Camera
from fmgs.errors import BackendUnavailableError
from fmgs.render.types import RasterConfig, RenderOutput

TILE_BATCHES = 8
"""With a ``between_tiles`` hook, tiles are blended in this many batches (a stop is seen within about
1/8 of a render)."""


def load_kernels(module: str = "cpu_kernels"):
    """Import a numba kernel module of fmgs.render on first use (numba is imported only then)."""
    try:
        return importlib.import_module(f"fmgs.render.{module}")
    except ImportError as e:  # pragma: no cover - numba is a core dependency
        raise BackendUnavailableError(f"the cpu backend needs numba ({e}); pip install 'fmgs[core]'") from e


def costliest_tiles_first(offsets: np.ndarray) -> np.ndarray:
    """Non-empty tile ids by descending list length (offsets [T+1]), so the threads finish together."""
    lens = np.diff(offsets)
    return np.argsort(-lens, kind="stable")[: int((lens > 0).sum())]


@functools.lru_cache(maxsize=8)
def _exp_table(alpha_min: float) -> np.ndarray:
    return load_kernels().exp_table(alpha_min)


def _np(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy())


def f64_array(t: torch.Tensor) -> np.ndarray:
    """A contiguous float64 numpy copy (or view) of a tensor, detached and on the CPU."""
    return np.ascontiguousarray(t.detach().cpu().to(torch.float64).numpy())


def _geom(t: torch.Tensor) -> np.ndarray:
    """Geometry as float32 or float64 without a copy; the kernels widen every value to float64."""
    return _np(t) if t.dtype in (torch.float32, torch.float64) else f64_array(t)


def project_cpu(
    means, quats, scales, opacities, camera: Camera, config: RasterConfig
) -> dict[str, np.ndarray]:
    """Run the projection kernel; returns float64/int numpy arrays keyed like fmgs.render.types.Projection."""
    k = load_kernels()
    n = means.shape[0]
    out = {
        "means2d": np.empty((n, 2)),
        "depths": np.empty(n),
        "conics": np.empty((n, 3)),
        "radii": np.empty(n, dtype=np.int32),
        "bbox": np.empty((n, 4), dtype=np.int64),
        "tbox": np.zeros((n, 4), dtype=np.int64),
        "visible": np.empty(n, dtype=np.bool_),
        "pmax": np.empty(n),
    }
    V = camera.viewmat.numpy()
    k.project_kernel(
        *(_geom(x) for x in (means, quats, scales, opacities)),
        np.ascontiguousarray(V[:3, :3]),
        np.ascontiguousarray(V[:3, 3]),
        camera.fx, camera.fy, camera.cx, camera.cy,
        float(camera.width), float(camera.height), camera.near, camera.far,
        config.fov_clip, config.eps2d, config.alpha_min, config.tile_size,
        *(out[key] for key in ("means2d", "depths", "conics", "radii", "bbox", "tbox", "visible", "pmax")),
    )  # fmt: skip
    return out


def rasterize_cpu(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    camera: Camera,
    background: torch.Tensor | None = None,
    config: RasterConfig = RasterConfig(),
    between_tiles: Callable[[], None] | None = None,
) -> RenderOutput:
    """Same contract as fmgs.render.rasterize; CPU tensors, no gradients.

    With ``between_tiles`` the tiles are blended in TILE_BATCHES batches of the costliest-first order
    (tiles are independent, so the image is the same) and it is called after each; it may raise.
    """
    import numba

    k = load_kernels()
    N, D = features.shape
    W, H, T = camera.width, camera.height, config.tile_size
    p = project_cpu(means, quats, scales, opacities, camera, config)
    vis = np.flatnonzero(p["visible"])
    order = vis[k.stable_argsort_positive(p["depths"][vis])]  # visible depths are > near > 0
    tiles_x, tiles_y = -(-W // T), -(-H // T)
    ids, offsets = k.bin_kernel(order, p["tbox"], tiles_x, tiles_y)
    tile_order = costliest_tiles_first(offsets)  # handed out one at a time
    feats = _geom(features)  # float16/bfloat16 features are widened (numba has no half arithmetic)
    out_dtype = feats.dtype
    image = np.zeros((H, W, D), dtype=out_dtype)
    alpha = np.zeros((H, W))
    depth = np.zeros((H, W))
    bg = f64_array(background) if background is not None else np.zeros(D)
    if background is not None:
        image[:] = bg.astype(out_dtype)  # tiles with no Gaussian see only the background
    pair_cnt = np.zeros(len(ids), dtype=np.int64)
    pair_w = np.zeros(len(ids))
    batches = [tile_order] if between_tiles is None else np.array_split(tile_order, TILE_BATCHES)
    for batch in batches:
        with numba.parallel_chunksize(1):
            k.raster_kernel(
                ids, offsets, np.ascontiguousarray(batch), T, tiles_x, W, H,
                p["means2d"], p["conics"], _geom(opacities), p["depths"], p["pmax"], p["bbox"],
                feats, bg, background is not None,
                config.alpha_max, config.alpha_min, config.transmittance_min, _exp_table(config.alpha_min),
                image, alpha, depth, pair_cnt, pair_w,
            )  # fmt: skip
        if between_tiles is not None:
            between_tiles()
    n_contrib = np.bincount(ids, weights=pair_cnt, minlength=N).astype(np.int32)
    weight_sum = np.bincount(ids, weights=pair_w, minlength=N)
    t = torch.from_numpy
    return RenderOutput(
        image=t(image).to(features.dtype),
        alpha=t(alpha).to(features.dtype),
        depth=t(depth).to(features.dtype),
        radii=t(p["radii"]),
        means2d=t(p["means2d"]),
        visible=t(p["visible"]),
        n_contrib=t(n_contrib),
        weight_sum=t(weight_sum),
    )
