"""Floaters counted against the sparse points a training camera sees (fmgs.train.floaters)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from fmgs.cameras import Camera
from fmgs.data.dataset import Frame, PosedDataset
from fmgs.gaussians import GaussianSet
from fmgs.train.floaters import MIN_POINTS, NEAR_MARGIN, floater_mask
from tests.helpers.scenes import look_at

W = H = 64
FOCAL = 50.0  # the image spans x, y in [-3.2, 3.2] at depth 5


def _dataset(points: np.ndarray | None, eye=(0.0, 0.0, 0.0)) -> PosedDataset:
    K = torch.tensor([[FOCAL, 0, W / 2], [0, FOCAL, H / 2], [0, 0, 1.0]], dtype=torch.float64)
    cam = Camera(K, look_at(eye, (eye[0], eye[1], eye[2] + 1.0)), W, H)
    return PosedDataset(Path("."), [Frame("a.png", Path("a.png"), cam)], points)


def _wall(n: int = 20, z: float = 5.0, stray: bool = True, back: bool = True) -> np.ndarray:
    """n x n sparse points on the plane at depth z; with ``back`` as many behind the camera (at z = -3: the
    scene surrounds it, as a room does), with ``stray`` one mistriangulated point near the camera."""
    xs = np.linspace(-2.0, 2.0, n)
    xy = np.stack(np.meshgrid(xs, xs), -1).reshape(-1, 2)
    layers = [np.concatenate([xy, np.full((len(xy), 1), d)], 1) for d in ((z, -3.0) if back else (z,))]
    return np.concatenate(layers + ([[[0.1, 0.1, 0.5]]] if stray else []))


def _gaussians(means, opacities) -> GaussianSet:
    n = len(means)
    return GaussianSet.from_activated(
        torch.tensor(means, dtype=torch.float32),
        torch.tensor([[1.0, 0, 0, 0]] * n),
        torch.full((n, 3), 0.01),
        torch.tensor(opacities, dtype=torch.float32),
        colors=torch.full((n, 3), 0.5),
    )


MEANS = [
    (0.0, 0.0, 5.0),  # on the wall
    (0.5, 0.5, 4.5),  # just in front of it (0.9 of its depth): within the margin
    (0.0, 0.0, 2.0),  # a floater
    (-1.0, 1.0, 3.0),  # a floater
    (10.0, 0.0, 2.0),  # near, but outside the image (and beyond the sparse points, sideways)
    (0.0, 0.0, -1.0),  # behind the camera
    (0.0, 0.0, 50.0),  # far beyond every sparse point
]
OPACITY = [0.9, 0.8, 0.7, 0.2, 0.6, 0.5, 0.4]


def test_gaussians_in_front_of_the_nearest_sparse_points_are_floaters():
    g = _gaussians(MEANS, OPACITY)
    mask, rep = floater_mask(g, _dataset(_wall()), views=[0])
    assert mask.tolist() == [False, False, True, True, False, False, False]  # the stray point hides none
    assert rep.count == 2 and rep.total == 7 and rep.cameras_checked == 1 and rep.margin == NEAR_MARGIN
    assert abs(rep.opacity - 0.9) < 1e-6
    assert rep.beyond == 2 and abs(rep.beyond_opacity - 1.0) < 1e-6
    assert rep.per_view == [{"name": "a.png", "floaters": 2, "near": 5.0}]
    assert "2 of 7 Gaussians" in rep.line() and "a.png" in rep.line() and "2 (opacity sum 1.0)" in rep.line()
    s = rep.summary()
    assert (
        s["count"] == 2 and s["fraction"] == 2 / 7 and s["beyond"] == 2 and s["worst_views"] == rep.per_view
    )
    # A wider margin takes the Gaussian just in front of the wall too.
    wide, _ = floater_mask(g, _dataset(_wall()), views=[0], margin=0.95)
    assert wide.tolist() == [False, True, True, True, False, False, False]


def test_each_camera_has_its_own_bound():
    # A second camera behind the wall, looking back at it: (0, 0, 7) lies in front of the wall for it only.
    ds = _dataset(_wall())
    K = ds.frames[0].camera.K
    back = Camera(K, look_at((0.0, 0.0, 10.0), (0.0, 0.0, 0.0)), W, H)
    ds.frames.append(Frame("b.png", Path("b.png"), back))
    g = _gaussians([(0.0, 0.0, 7.0), (0.0, 0.0, 2.0), (0.0, 0.0, 5.0)], [0.5, 0.5, 0.5])
    mask, rep = floater_mask(g, ds, views=[0, 1])
    assert mask.tolist() == [True, True, False] and rep.cameras_checked == 2
    assert sorted((r["name"], r["floaters"], r["near"]) for r in rep.per_view) == [
        ("a.png", 1, 5.0), ("b.png", 1, 5.0)
    ]  # fmt: skip
    only_a, _ = floater_mask(g, ds, views=[0])
    assert only_a.tolist() == [False, True, False]


def test_no_sparse_points_checks_nothing():
    g = _gaussians(MEANS, OPACITY)
    for pts in (None, _wall(n=5, stray=False, back=False)[: MIN_POINTS - 1]):
        mask, rep = floater_mask(g, _dataset(pts), views=[0])
        assert not mask.any() and rep.count == 0 and rep.cameras_checked == 0
        assert "not checked" in rep.line()
    # Enough points, but none in this camera's view: no bound for it.
    mask, rep = floater_mask(
        g, _dataset(_wall(stray=False, back=False) * np.array([1.0, 1.0, -1.0])), views=[0]
    )
    assert not mask.any() and rep.cameras_checked == 0


def test_the_training_views_are_the_default():
    # One frame is all held out (frame 0 of every 8): no training camera, nothing checked.
    mask, rep = floater_mask(_gaussians(MEANS, OPACITY), _dataset(_wall()))
    assert not mask.any() and rep.cameras_checked == 0 and rep.beyond == 2
