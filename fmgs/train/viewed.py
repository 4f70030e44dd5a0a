"""Initial points for a dataset without sparse points: the volume the cameras look at together.

The box of the camera centres is the wrong place: a ring of cameras above a table holds no table,
and random Gaussians there trained a tabletop capture to 13 dB held-out (31 dB with points). Instead:
1. the focus is the point nearest (least squares) to every camera's optical axis;
2. candidates are drawn uniformly in the cube around it whose half-edge is the farthest camera's
   distance to it;
3. a candidate is kept when it lies in front of, and inside the image of, at least ``min_share`` of
   the largest number of cameras any candidate is seen by: the cameras' common view;
4. with images, each point takes its mean colour over the images that see it (occlusion ignored),
   and a background colour the dataset declares carves: a point that any image shows as background is
   empty space (the visual hull). Ranking points by photo-consistency instead was tried and placed
   them farther from the surfaces than uniform draws (median 1.0 against 0.73 scene units on a
   rendered tabletop): far, blurred floor looks uniform, so points below the floor looked consistent.

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
    colours: np.ndarray | None = None
    """[n,3] mean colour in [0,1] over the images that see each point (None without images)."""


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


def _project(points: np.ndarray, cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates u [n], v [n] of points [n,3] in ``cam`` and whether each is in front of it
    (beyond ``near``) and inside its image [n]."""
    V = cam.viewmat.double().numpy()
    K = cam.K.double().numpy()
    x = points @ V[:3, :3].T + V[:3, 3]
    z = x[:, 2]
    front = z > cam.near
    zs = np.where(front, z, 1.0)
    u = K[0, 0] * x[:, 0] / zs + K[0, 2]
    v = K[1, 1] * x[:, 1] / zs + K[1, 2]
    return u, v, front & (u >= 0) & (u <= cam.width) & (v >= 0) & (v <= cam.height)


def seen_by(points: np.ndarray, cameras: Sequence[Camera], chunk: int = 65536) -> np.ndarray:
    """[n] int64 number of cameras each of points [n,3] is in front of (beyond ``near``) and inside
    the image of."""
    count = np.zeros(len(points), np.int64)
    for cam in cameras:
        for s in range(0, len(points), chunk):
            count[s : s + chunk] += _project(points[s : s + chunk], cam)[2]
    return count


BACKGROUND_TOLERANCE = 0.02
"""A pixel within this of the declared background colour (every channel, colours in [0,1]) is background."""


def colour_spread(
    points: np.ndarray,
    cameras: Sequence[Camera],
    images: Sequence[np.ndarray],
    background: Sequence[float] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean colour [n,3], colour variance [n] (summed over channels) of points [n,3] over the images
    [H,W,3] (each matching its camera's size) they are seen in, nearest pixel, and whether any of them
    shows ``background`` there [n] (never without one); points seen in no image get mean 0.5 and
    variance +inf."""
    n = len(points)
    s1, s2, cnt = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n)
    empty = np.zeros(n, dtype=bool)
    bg = None if background is None else np.asarray(background, np.float64)
    for cam, img in zip(cameras, images, strict=True):
        if img.shape[:2] != (cam.height, cam.width):
            raise ValidationError(
                "images", f"{img.shape[:2]} does not match its camera {cam.height}x{cam.width}"
            )
        u, v, ok = _project(points, cam)
        j = np.clip(np.floor(u[ok]).astype(np.int64), 0, cam.width - 1)
        i = np.clip(np.floor(v[ok]).astype(np.int64), 0, cam.height - 1)
        c = img[i, j].astype(np.float64)
        if bg is not None:
            empty[ok] |= (np.abs(c - bg) <= BACKGROUND_TOLERANCE).all(1)
        s1[ok] += c
        s2[ok] += c * c
        cnt[ok] += 1
    seen = cnt > 0
    mean = np.full((n, 3), 0.5)
    mean[seen] = s1[seen] / cnt[seen, None]
    var = np.full(n, np.inf)
    var[seen] = np.maximum(s2[seen] / cnt[seen, None] - mean[seen] ** 2, 0.0).sum(1)
    return mean, var, empty


def viewed_points(
    cameras: Sequence[Camera],
    n: int,
    seed: int,
    min_share: float = 0.5,
    max_rounds: int = 64,
    images: Sequence[np.ndarray] | None = None,
    image_cameras: Sequence[Camera] | None = None,
    background: Sequence[float] | None = None,
) -> ViewedVolume:
    """``n`` points drawn uniformly from the cameras' common view (module docstring); with ``images``
    ([H,W,3] in [0,1], taken by ``image_cameras``) each gets its mean colour there, and with a
    ``background`` colour too, what any image shows as background is carved away first."""
    if n < 1:
        raise ValidationError("n", f"must be positive, got {n}")
    if images is not None and (image_cameras is None or len(image_cameras) != len(images)):
        raise ValidationError("images", "need one camera per image")
    carve = images is not None and background is not None
    focus = focus_point(cameras)
    centres, _ = _axes(cameras)
    half = float(np.linalg.norm(centres - focus, axis=1).max())
    rng = np.random.default_rng(seed)
    batch = max(4 * n, 16384)
    pts: list[np.ndarray] = []
    by: list[np.ndarray] = []
    got, need = 0, None
    for _ in range(max_rounds):
        cand = rng.uniform(focus - half, focus + half, size=(batch, 3))
        cnt = seen_by(cand, cameras)
        if need is None:  # the common view's threshold comes from the first batch
            need = max(1, int(np.ceil(min_share * cnt.max())))
        keep = cnt >= need
        if carve:
            keep[keep] = ~colour_spread(cand[keep], image_cameras, images, background)[2]
        pts.append(cand[keep])
        by.append(cnt[keep])
        got += int(keep.sum())
        if got >= n:
            break
    p, b = np.concatenate(pts)[:n], np.concatenate(by)[:n]
    if len(p) < n:
        what = "outside the background" if carve else ""
        raise ValidationError("cameras", f"their common view {what} is too thin to hold {n} points")
    colours = None if images is None else colour_spread(p, image_cameras, images)[0]
    return ViewedVolume(focus, half, p, b, colours)
