"""The points-free initialisation: Gaussians in the volume the cameras look at together."""

from __future__ import annotations

import dataclasses
import json
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


def test_colour_spread_equals_one_point_at_a_time():
    from fmgs.train.viewed import colour_spread

    cams = _tabletop(5)
    rng = np.random.default_rng(4)
    images = [rng.uniform(0, 1, size=(48, 64, 3)) for _ in cams]
    pts = rng.uniform(-3, 3, size=(300, 3))
    pts[0] = (0.3, -0.2, 0.25)
    bg = np.array([0.2, 0.4, 0.6])
    images[2][:, :32] = bg  # half of one image shows the declared background: carves what lies there
    mean, var, empty = colour_spread(pts, cams, images, bg)
    assert (
        np.array_equal(colour_spread(pts, cams, images)[1], var)
        and not colour_spread(pts, cams, images)[2].any()
    )
    for p, m, v, e in zip(pts, mean, var, empty, strict=True):
        seen = []
        for cam, img in zip(cams, images, strict=True):
            if _seen_by_reference(p, cam):
                x = cam.viewmat.double().numpy() @ np.append(p, 1.0)
                u, w = cam.fx * x[0] / x[2] + cam.cx, cam.fy * x[1] / x[2] + cam.cy
                seen.append(img[min(int(w), cam.height - 1), min(int(u), cam.width - 1)])
        assert e == any(np.abs(c - bg).max() <= 0.02 for c in seen)
        if not seen:
            assert v == np.inf and np.all(m == 0.5)
            continue
        c = np.array(seen)
        np.testing.assert_allclose(m, c.mean(0), atol=1e-12)
        np.testing.assert_allclose(v, c.var(0).sum(), atol=1e-12)
    assert np.isinf(var).any() and np.isfinite(var).sum() > 100 and empty.sum() >= 1


def test_a_declared_background_carves_the_air_and_images_colour_the_points(tmp_path):
    """On a rendered tabletop, carving what any image shows as sky keeps the table and the objects
    (more of the kept points lie on a surface than of uniform draws, none above the scene's top), and
    points on a surface take its colour."""
    from scipy.spatial import cKDTree

    from fmgs.data.dataset import load_dataset
    from fmgs.synth import SynthConfig, generate

    generate(tmp_path, SynthConfig(views=16, width=64, height=48, points=20000))
    ds = load_dataset(tmp_path)
    cams = [f.camera for f in ds.frames]
    images = [ds.image(i)[0].numpy() for i in range(len(ds))]
    bg = json.loads((tmp_path / "transforms.json").read_text())["background"]
    uniform = viewed_points(cams, 4000, seed=0)
    carved = viewed_points(cams, 4000, seed=0, images=images, image_cameras=cams, background=bg)
    assert uniform.colours is None and carved.points.shape == (4000, 3)
    surface = cKDTree(ds.points)
    on = lambda v: np.mean(surface.query(v.points)[0] < 0.1)  # noqa: E731
    assert on(carved) > 1.5 * on(uniform), (on(carved), on(uniform))
    top = ds.points[:, 2].max()
    assert (uniform.points[:, 2] > top + 0.3).mean() > 0.1 and (carved.points[:, 2] > top + 0.3).mean() < 0.01
    assert (0 <= carved.colours).all() and (carved.colours <= 1).all()
    d, nearest = surface.query(carved.points)
    near = d < 0.03
    true = ds.colors[nearest[near]].astype(np.float64) / 255
    err = np.median(np.abs(carved.colours[near] - true).sum(1))
    random_err = np.median(np.abs(np.random.default_rng(0).uniform(0, 1, true.shape) - true).sum(1))
    assert near.sum() > 50 and err < 0.3 and err < 0.3 * random_err, (err, random_err)
