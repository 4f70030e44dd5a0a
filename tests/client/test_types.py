"""The client's value types (``fmgs_client.types``): cameras built with look_at, their projection and
their wire form."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from fmgs_client.types import CameraSpec


@given(
    eye=hnp.arrays(np.float64, 3, elements=st.floats(-50, 50)),
    target=hnp.arrays(np.float64, 3, elements=st.floats(-50, 50)),
    up=st.sampled_from([(0, 0, 1), (0, -1, 0), (1, 1, 0)]),
)
def test_look_at(eye, target, up):
    if np.linalg.norm(target - eye) < 1e-3:
        return
    cam = CameraSpec.look_at(eye, target, up, width=64, height=48, fov_deg=70)
    R = cam.viewmat[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_array_equal(cam.viewmat[3], [0, 0, 0, 1])
    uv, z = cam.project(target[None])
    np.testing.assert_allclose(uv[0], [32, 24], atol=1e-6 * max(1, np.abs(eye).max()))
    assert z[0] == pytest.approx(np.linalg.norm(target - eye))
    np.testing.assert_allclose(cam.eye, eye, atol=1e-9 * max(1, np.abs(eye).max()))
    # Up in the world is up in the image (smaller y) unless looking along it.
    u = np.asarray(up, float) / np.linalg.norm(up)
    d = (target - eye) / np.linalg.norm(target - eye)
    if abs(d @ u) < 0.9:
        uv_up, _ = cam.project((target + 0.01 * np.linalg.norm(target - eye) * u)[None])
        assert uv_up[0, 1] < 24
    back = CameraSpec.from_proto(cam.to_proto())
    np.testing.assert_array_equal(back.viewmat, cam.viewmat)
    assert (back.fx, back.cx, back.width, back.height) == (cam.fx, cam.cx, 64, 48)


def test_look_at_degenerate():
    cam = CameraSpec.look_at((0, 0, 5), (0, 0, 0), (0, 0, 1))  # straight down along up
    R = cam.viewmat[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    with pytest.raises(ValueError, match="distinct"):
        CameraSpec.look_at((1, 1, 1), (1, 1, 1))
    with pytest.raises(ValueError, match="viewmat"):
        CameraSpec(np.eye(3), 1, 1, 1, 1, 2, 2)


@pytest.mark.parametrize("up", [(float("nan"), 0, 1), (0, float("inf"), 1)])
def test_look_at_names_a_non_finite_up(up):
    with pytest.raises(ValueError, match="up"):
        CameraSpec.look_at((0, -3, 1), (0, 0, 0), up)
