"""The points-free initialisation: Gaussians in the volume the cameras look at together."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from fmgs.cameras import Camera
from fmgs.errors import ValidationError
from fmgs.synth import _look_at
from fmgs.train.config import GSTrainConfig
from fmgs.train.viewed import focus_point, seen_by, viewed_points


def _camera(eye, target, w=64, h=48, fov_deg=55.0) -> Camera:
    f = 0.5 * w / math.tan(math.radians(fov_deg) / 2)
    K = torch.tensor([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]], dtype=torch.float64)
    return Camera(K, torch.from_numpy(_look_at(np.asarray(eye, float), np.asarray(target, float))), w, h)


def _tabletop(n=24, target=(0.3, -0.2, 0.25)) -> list[Camera]:
    """A ring of cameras 0.9-1.6 above a table at z = 0, all looking at ``target``."""
    cams = []
    for v in range(n):
        a = 2 * np.pi * v / n
        eye = (4 * np.cos(a) + target[0], 4 * np.sin(a) + target[1], 0.9 if v % 2 == 0 else 1.6)
        cams.append(_camera(eye, target))
    return cams


def _seen_by_reference(p: np.ndarray, cam: Camera) -> bool:
    """One point, one camera, through Camera's own world-to-camera matrix."""
    x = cam.viewmat.double().numpy() @ np.append(p, 1.0)
    if x[2] <= cam.near:
        return False
    u, v = cam.fx * x[0] / x[2] + cam.cx, cam.fy * x[1] / x[2] + cam.cy
    return 0 <= u <= cam.width and 0 <= v <= cam.height


def test_focus_is_where_the_axes_meet():
    np.testing.assert_allclose(focus_point(_tabletop()), [0.3, -0.2, 0.25], atol=1e-9)


def test_seen_by_equals_one_point_at_a_time():
    cams = _tabletop(8)
    pts = np.random.default_rng(1).uniform(-5, 5, size=(400, 3))
    pts[0] = (0.3, -0.2, 0.25)  # the focus: every camera
    want = np.array([sum(_seen_by_reference(p, c) for c in cams) for p in pts])
    got = seen_by(pts, cams, chunk=37)  # chunks that do not divide the points
    assert np.array_equal(got, want) and got[0] == 8 and 0 < got.min() + 1 and (got == 0).any()


def test_points_fill_the_common_view_not_the_cameras_box():
    cams = _tabletop()
    vol = viewed_points(cams, 5000, seed=3)
    p = vol.points
    assert p.shape == (5000, 3) and np.isfinite(p).all()
    assert (vol.seen_by >= math.ceil(0.5 * vol.seen_by.max())).all()
    assert np.array_equal(vol.seen_by, seen_by(p, cams))
    # The table (z = 0) lies below every camera (z >= 0.9): the centres' box held none of it.
    assert (np.abs(p[:, 2]) < 0.1).sum() > 100
    assert (p[:, 2] < 0.9).mean() > 0.5
    # Centred on the focus, and nowhere near as wide as the ring.
    assert np.linalg.norm(p.mean(0) - [0.3, -0.2, 0.25]) < 0.3
    assert np.linalg.norm(p[:, :2] - [0.3, -0.2], axis=1).max() < 4.0
    again = viewed_points(cams, 5000, seed=3)
    assert np.array_equal(again.points, p)  # seeded


def test_cameras_that_share_no_focus_are_refused_with_what_to_supply(tmp_path):
    from fmgs.data.dataset import load_dataset
    from fmgs.synth import SynthConfig, generate
    from fmgs.train.gaussians import init_params

    generate(tmp_path, SynthConfig(views=6, width=32, height=24, points=500))
    tiny_scene = tmp_path

    forward = [_camera((x, 0.0, 1.0), (x, 5.0, 1.0)) for x in np.linspace(-1, 1, 6)]  # all look +y
    with pytest.raises(ValidationError, match="do not converge"):
        focus_point(forward)
    ds = load_dataset(tiny_scene)
    frames = [dataclasses.replace(f, camera=c) for f, c in zip(ds.frames, forward, strict=False)]
    ds = dataclasses.replace(ds, points=None, colors=None, frames=frames)
    with pytest.raises(ValidationError, match="give the dataset points"):
        init_params(ds, GSTrainConfig(random_init=100), torch.Generator())
