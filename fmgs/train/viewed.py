"""Initial points for a dataset without sparse points: the volume the cameras look at together.

The box of the camera centres is the wrong place: a ring of cameras above a table holds no table,
and random Gaussians there trained a tabletop capture to 13 dB held-out (31 dB with points). Instead:
1. the focus is the point nearest (least squares) to every camera's optical axis;
2. candidates are drawn uniformly in the cube around it whose half-edge is the farthest camera's
   distance to it;
3. a candidate is kept when it lies in front of, and inside the image of, at least ``min_share`` of
   the largest number of cameras any candidate is seen by: the cameras' common view.

Cameras whose axes do not converge (all looking the same way, as in a forward-facing capture) have
no focus; ``viewed_points`` then raises and the caller says what to supply.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fmgs.cameras import Camera
from fmgs.errors import ValidationError


@dataclass(frozen=True)
class ViewedVolume:
    """Where the cameras look together."""

    focus: np.ndarray
    """[3] point nearest to every optical axis."""
    half_edge: float
    """Half-edge of the cube candidates are drawn from (farthest camera to the focus)."""
    points: np.ndarray
    """[n,3] float64 points in the common view."""
    seen_by: np.ndarray
    """[n] int64 cameras each point is in front of and inside the image of."""


def _axes(cameras: Sequence[Camera]) -> tuple[np.ndarray, np.ndarray]:
    """Centres [V,3] and unit forward directions [V,3] (OpenCV +z) in world space."""
    V = np.stack([c.viewmat.double().numpy() for c in cameras])
    R, t = V[:, :3, :3], V[:, :3, 3]
    centres = -np.einsum("vji,vj->vi", R, t)  # -R^T t
    forward = R[:, 2, :]  # the third row of R is the camera's +z in world space
    return centres, forward / np.linalg.norm(forward, axis=1, keepdims=True)


def focus_point(cameras: Sequence[Camera], min_conditioning: float = 1e-3) -> np.ndarray:
    """[3] least-squares point nearest to every optical axis; ValidationError when the axes are
    (nearly) parallel, so that no such point is determined."""
    c, d = _axes(cameras)
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # projectors onto each axis's normal plane
    A, b = P.sum(0), np.einsum("vij,vj->i", P, c)
    w = np.linalg.eigvalsh(A)
    if len(cameras) < 2 or w[0] <= min_conditioning * w[-1]:
        raise ValidationError(
            "cameras", "their optical axes do not converge on a common point (a forward-facing capture?)"
        )
    return np.linalg.solve(A, b)


def seen_by(points: np.ndarray, cameras: Sequence[Camera], chunk: int = 65536) -> np.ndarray:
    """[n] int64 number of cameras each of points [n,3] is in front of (beyond ``near``) and inside
    the image of."""
    count = np.zeros(len(points), np.int64)
    for cam in cameras:
        V = cam.viewmat.double().numpy()
        K = cam.K.double().numpy()
        for s in range(0, len(points), chunk):
            x = points[s : s + chunk] @ V[:3, :3].T + V[:3, 3]
            z = x[:, 2]
            front = z > cam.near
            zs = np.where(front, z, 1.0)
            u = K[0, 0] * x[:, 0] / zs + K[0, 2]
            v = K[1, 1] * x[:, 1] / zs + K[1, 2]
            inside = front & (u >= 0) & (u <= cam.width) & (v >= 0) & (v <= cam.height)
            count[s : s + chunk] += inside
    return count


def viewed_points(
    cameras: Sequence[Camera], n: int, seed: int, min_share: float = 0.5, max_rounds: int = 64
) -> ViewedVolume:
    """``n`` points drawn uniformly from the cameras' common view (module docstring)."""
    if n < 1:
        raise ValidationError("n", f"must be positive, got {n}")
    focus = focus_point(cameras)
    centres, _ = _axes(cameras)
    half = float(np.linalg.norm(centres - focus, axis=1).max())
    rng = np.random.default_rng(seed)
    batch = max(4 * n, 16384)
    # The common view's threshold comes from a first batch; later batches only fill it.
    cand = rng.uniform(focus - half, focus + half, size=(batch, 3))
    cnt = seen_by(cand, cameras)
    need = max(1, int(np.ceil(min_share * cnt.max())))
    pts, by = [cand[cnt >= need]], [cnt[cnt >= need]]
    got = len(pts[0])
    for _ in range(max_rounds):
        if got >= n:
            break
        cand = rng.uniform(focus - half, focus + half, size=(batch, 3))
        cnt = seen_by(cand, cameras)
        pts.append(cand[cnt >= need])
        by.append(cnt[cnt >= need])
        got += len(pts[-1])
    p, b = np.concatenate(pts)[:n], np.concatenate(by)[:n]
    if len(p) < n:
        raise ValidationError("cameras", f"their common view is too thin to hold {n} points")
    return ViewedVolume(focus, half, p, b)
