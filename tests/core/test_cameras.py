"""Cameras: OpenCV convention, COLMAP and OpenGL (transforms.json) converters, validation."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from fmgs.cameras import Camera, quat_wxyz_to_rotmat
from fmgs.errors import ValidationError
from tests.helpers.scenes import look_at


def test_colmap_and_transforms_json_give_the_same_cameras(data_dir):
    """snowmiku_small ships the same poses as a COLMAP model and as transforms.json (OpenGL c2w)."""
    root = data_dir / "snowmiku_small"
    cam_line = next(
        line
        for line in (root / "sparse/0/cameras.txt").read_text().splitlines()
        if line and not line.startswith("#")
    )
    _, model, w, h, *params = cam_line.split()
    colmap = {}
    for line in (root / "sparse/0/images.txt").read_text().splitlines():
        parts = line.split()
        if len(parts) == 10 and not line.startswith("#"):
            q, t = [float(x) for x in parts[1:5]], [float(x) for x in parts[5:8]]
            colmap[parts[9]] = Camera.from_colmap(q, t, model, [float(p) for p in params], int(w), int(h))
    meta = json.loads((root / "transforms.json").read_text())
    K = Camera.intrinsics(meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"])
    assert len(meta["frames"]) == len(colmap) == 97
    for fr in meta["frames"]:
        cam = Camera.from_opengl_c2w(torch.tensor(fr["transform_matrix"]), K, meta["w"], meta["h"])
        ref = colmap[fr["file_path"].split("/")[-1]]
        assert torch.allclose(cam.viewmat, ref.viewmat, atol=1e-9)
        assert torch.allclose(cam.K, ref.K, atol=1e-9)


def test_projection_convention():
    """A point on the optical axis lands on the principal point; +x right, +y down (OpenCV)."""
    cam = Camera(Camera.intrinsics(100, 100, 50, 40), torch.eye(4), 100, 80)
    assert torch.equal(cam.center, torch.zeros(3, dtype=torch.float64))
    V = look_at([0.0, 0.0, -5.0], [0, 0, 0])  # camera on -z looking at the origin, y down
    cam = Camera(Camera.intrinsics(100, 100, 50, 40), V, 100, 80)
    assert torch.allclose(cam.center, torch.tensor([0.0, 0.0, -5.0], dtype=torch.float64))
    p = cam.viewmat @ torch.tensor([1.0, 1.0, 0.0, 1.0], dtype=torch.float64)
    assert p[2] == pytest.approx(5.0)


def test_opengl_conversion_flips_y_and_z():
    c2w_gl = torch.eye(4, dtype=torch.float64)
    c2w_gl[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    cam = Camera.from_opengl_c2w(c2w_gl, Camera.intrinsics(10, 10, 5, 5), 10, 10)
    # An OpenGL camera looks down -z: the world point 1 unit along -z is straight ahead at depth 1.
    p = cam.viewmat @ torch.tensor([1.0, 2.0, 2.0, 1.0], dtype=torch.float64)
    assert torch.allclose(p[:3], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    up = cam.viewmat @ torch.tensor([1.0, 3.0, 3.0, 1.0], dtype=torch.float64)  # world +y is image up
    assert up[1] < 0


def test_quaternion_to_rotation():
    q = torch.randn(100, 4, dtype=torch.float64)
    R = quat_wxyz_to_rotmat(q)
    eye = torch.eye(3, dtype=torch.float64).expand(100, 3, 3)
    assert torch.allclose(R @ R.transpose(1, 2), eye, atol=1e-12)
    assert torch.allclose(torch.det(R), torch.ones(100, dtype=torch.float64))
    # 90 degrees about z: x -> y
    s = 2**-0.5
    Rz = quat_wxyz_to_rotmat(torch.tensor([s, 0, 0, s], dtype=torch.float64))
    assert torch.allclose(
        Rz @ torch.tensor([1.0, 0, 0], dtype=torch.float64),
        torch.tensor([0.0, 1, 0], dtype=torch.float64),
        atol=1e-15,
    )


def test_scaled_camera():
    cam = Camera(Camera.intrinsics(100, 90, 50, 40), torch.eye(4), 100, 80)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (50, 40)
    assert half.fx == 50 and half.cy == 20


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        (dict(width=0), "width"),
        (dict(height=-3), "height"),
        (dict(K=torch.diag(torch.tensor([-1.0, 1.0, 1.0]))), "K"),
        (dict(viewmat=torch.diag(torch.tensor([1.0, 1.0, -1.0, 1.0]))), "viewmat"),
        (dict(viewmat=2 * torch.eye(4)), "viewmat"),
        (dict(near=0.0), "near"),
        (dict(K=torch.zeros(2, 2)), "K"),
    ],
)
def test_camera_validation_names_the_field(kwargs, field):
    args = dict(K=Camera.intrinsics(10, 10, 5, 5), viewmat=torch.eye(4), width=10, height=10) | kwargs
    with pytest.raises(ValidationError, match=rf"^{field}"):
        Camera(**args)


def test_colmap_models():
    q, t = [1.0, 0, 0, 0], [0.0, 0, 0]
    cam = Camera.from_colmap(q, t, "SIMPLE_PINHOLE", [300.0, 50.0, 40.0], 100, 80)
    assert cam.fx == cam.fy == 300.0
    cam = Camera.from_colmap(q, t, "OPENCV", [300.0, 310.0, 50.0, 40.0, 0, 0, 0, 0], 100, 80)
    assert cam.fy == 310.0
    with pytest.raises(ValidationError, match="undistort"):
        Camera.from_colmap(q, t, "OPENCV", [300.0, 310.0, 50.0, 40.0, 0.1, 0, 0, 0], 100, 80)
    with pytest.raises(ValidationError, match="unsupported"):
        Camera.from_colmap(q, t, "FISHEYE_WEIRD", [1.0], 100, 80)
    with pytest.raises(ValidationError, match="takes 4 parameters"):
        Camera.from_colmap(q, t, "PINHOLE", [1.0, 2.0], 100, 80)
    np.testing.assert_allclose(cam.camtoworld.numpy(), np.eye(4))


@pytest.mark.parametrize(
    "rot",
    [
        torch.zeros(3, 3),  # a blank pose: SVD would make it the identity
        torch.diag(torch.tensor([1.0, 1.0, 0.0])),  # rank 2: the sign of its det is a coin toss
        torch.diag(torch.tensor([1.0, 1.0, 1e-12])),  # numerically rank 2
        torch.tensor([[1.0, 0, 0], [1.0, 0, 0], [0, 0, 1.0]]),  # two equal rows
    ],
)
def test_opengl_c2w_with_a_singular_rotation_is_refused(rot):
    """transforms.json rotations may carry a scale (re-orthonormalised), but one that has lost a direction
    fixes no camera orientation: an error saying so, not an arbitrary camera or a 'reflection'."""
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = rot
    c2w[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    K = Camera.intrinsics(10, 10, 5, 5)
    with pytest.raises(ValidationError, match=r"^c2w.*singular"):
        Camera.from_opengl_c2w(c2w, K, 10, 10)
    # A uniformly scaled rotation still converts, to the rotation itself.
    q = quat_wxyz_to_rotmat(torch.tensor([0.9, 0.1, -0.3, 0.2], dtype=torch.float64))
    c2w[:3, :3] = 3.5 * q
    cam = Camera.from_opengl_c2w(c2w, K, 10, 10)
    c2w[:3, :3] = q
    assert torch.allclose(cam.viewmat, Camera.from_opengl_c2w(c2w, K, 10, 10).viewmat)
