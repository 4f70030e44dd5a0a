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
"""With a ``between_tiles`` hook, tiles are blended in at least this many batches."""
BATCH_PAIRS = 500_000
"""... and in batches of about this many (tile, Gaussian) pairs at most (one tile's list is never split),
so that a stop is seen within about 0.1 s of blending on a 2-core machine whatever the scene's size."""


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


def tile_batches(offsets: np.ndarray, tile_order: np.ndarray) -> list[np.ndarray]:
    """``tile_order`` cut into max(TILE_BATCHES, ceil(pairs / BATCH_PAIRS)) consecutive batches (some may
    be empty) of about equal pair counts (offsets [T+1] give each tile's list length)."""
    lens = np.diff(offsets)[tile_order]
    total = int(lens.sum())
    count = max(TILE_BATCHES, -(-total // BATCH_PAIRS))
    if count == TILE_BATCHES:
        return np.array_split(tile_order, TILE_BATCHES)
    return np.split(tile_order, np.searchsorted(np.cumsum(lens), np.arange(1, count) * (total / count)))


def bin_pairs(order: np.ndarray, tbox: np.ndarray, tiles_x: int, tiles_y: int) -> tuple[np.ndarray, ...]:
    """(ids, offsets) of the (tile, Gaussian) pairs, each tile's list front to back: the parallel counting
    sort over as many slices of ``order`` as numba has threads (bin_kernel is its serial twin)."""
    import numba

    k = load_kernels()
    chunks = max(1, min(numba.get_num_threads(), len(order) // 4096))
    if chunks == 1:
        return k.bin_kernel(order, tbox, tiles_x, tiles_y)
    return k.bin_kernel_parallel(order, tbox, tiles_x, tiles_y, chunks)


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

    With ``between_tiles`` the tiles are blended in batches of the costliest-first order (tile_batches;
    tiles are independent, so the image is the same) and it is called after projection, depth sorting,
    binning and each batch; it may raise.
    """
    import numba

    k = load_kernels()
    N, D = features.shape
    W, H, T = camera.width, camera.height, config.tile_size
    stop = between_tiles or (lambda: None)
    p = project_cpu(means, quats, scales, opacities, camera, config)
    stop()  # the stages before blending take seconds on a million Gaussians at the largest image
    vis = np.flatnonzero(p["visible"])
    order = vis[k.stable_argsort_positive(p["depths"][vis])]  # visible depths are > near > 0
    tiles_x, tiles_y = -(-W // T), -(-H // T)
    stop()
    ids, offsets = bin_pairs(order, p["tbox"], tiles_x, tiles_y)
    stop()
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
    batches = [tile_order] if between_tiles is None else tile_batches(offsets, tile_order)
    for batch in batches:
        with numba.parallel_chunksize(1):
            k.raster_kernel(
                ids, offsets, np.ascontiguousarray(batch), T, tiles_x, W, H,
                p["means2d"], p["conics"], _geom(opacities), p["depths"], p["pmax"], p["bbox"],
                feats, bg, background is not None,
                config.alpha_max, config.alpha_min, config.transmittance_min, _exp_table(config.alpha_min),
                image, alpha, depth, pair_cnt, pair_w,
            )  # fmt: skip
        stop()
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
