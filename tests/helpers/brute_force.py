"""Brute-force float64 renderer for tests: every Gaussian at every pixel, no tiles, no culling boxes.

Written independently of fmgs.render (numpy, explicit matrices) so the two can check each other.
The rendering rule is the documented one (RasterConfig): EWA projection with the Jacobian's x/z, y/z
clamped to the field of view plus fov_clip, eps2d dilation, alpha = min(alpha_max, o exp(-power/2)),
skipped below alpha_min, stop before the Gaussian that would bring the transmittance below
transmittance_min, pixel centres at (j + 0.5, i + 0.5).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from fmgs.render.types import RasterConfig


class BruteOutput(NamedTuple):
    image: np.ndarray  # [H,W,D]
    alpha: np.ndarray  # [H,W]
    depth: np.ndarray  # [H,W]
    n_contrib: np.ndarray  # [N]
    weight_sum: np.ndarray  # [N]


def _rotmat(q: np.ndarray) -> np.ndarray:
    q = q / np.abs(q).max()
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def brute_force_render(
    means,
    quats,
    scales,
    opacities,
    features,
    K,
    viewmat,
    width,
    height,
    near=0.01,
    far=1e10,
    background=None,
    config: RasterConfig = RasterConfig(),
) -> BruteOutput:
    """Render with plain float64 numpy; arguments as numpy-convertible arrays (see fmgs.render.rasterize)."""
    f = lambda a: np.asarray(a, dtype=np.float64)  # noqa: E731
    means, quats, scales, opacities, features = map(f, (means, quats, scales, opacities, features))
    K, V = f(K), f(viewmat)
    N, D = features.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    R, t = V[:3, :3], V[:3, 3]
    js, is_ = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)

    cam = means @ R.T + t
    order = np.argsort(cam[:, 2], kind="stable")
    image = np.zeros((height, width, D))
    acc_w = np.zeros((height, width))
    acc_z = np.zeros((height, width))
    T = np.ones((height, width))
    done = np.zeros((height, width), dtype=bool)
    n_contrib = np.zeros(N, dtype=np.int64)
    weight_sum = np.zeros(N)
    tanx, tany = 0.5 * width / fx, 0.5 * height / fy
    for g in order:
        x, y, z = cam[g]
        if not (near < z < far):
            continue
        tx = z * np.clip(
            x / z, -(cx / fx + config.fov_clip * tanx), (width - cx) / fx + config.fov_clip * tanx
        )
        ty = z * np.clip(
            y / z, -(cy / fy + config.fov_clip * tany), (height - cy) / fy + config.fov_clip * tany
        )
        J = np.array([[fx / z, 0, -fx * tx / z**2], [0, fy / z, -fy * ty / z**2]])
        L = _rotmat(quats[g]) @ np.diag(scales[g])
        cov = (J @ R @ L) @ (J @ R @ L).T + config.eps2d * np.eye(2)
        conic = np.linalg.inv(cov)
        u, v = fx * x / z + cx, fy * y / z + cy
        dx, dy = js - u, is_ - v
        power = conic[0, 0] * dx * dx + 2 * conic[0, 1] * dx * dy + conic[1, 1] * dy * dy
        alpha = np.minimum(config.alpha_max, opacities[g] * np.exp(-0.5 * power))
        hit = (alpha >= config.alpha_min) & ~done
        T_next = T * (1 - alpha)
        stop = hit & (T_next < config.transmittance_min)
        keep = hit & ~stop
        w = np.where(keep, alpha * T, 0.0)
        image += w[..., None] * features[g]
        acc_w += w
        acc_z += w * z
        T = np.where(keep, T_next, T)
        done |= stop
        n_contrib[g] = int((w > 0).sum())
        weight_sum[g] = w.sum()
    if background is not None:
        image += T[..., None] * f(background)
    depth = np.where(acc_w > 0, acc_z / np.where(acc_w > 0, acc_w, 1.0), 0.0)
    return BruteOutput(image, acc_w, depth, n_contrib, weight_sum)
