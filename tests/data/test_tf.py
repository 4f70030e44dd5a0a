"""The tf tree: composition along the tree, interpolation as tf2 does it, and the lookups it refuses."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from fmgs.data.tf import TfTree, invert, matrix_to_quat, quat_to_matrix, rigid, slerp
from fmgs.errors import ValidationError

S = 10**9


def _q(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(R).as_quat()  # x, y, z, w


def test_quaternion_conversions_match_scipy():
    rng = np.random.default_rng(0)
    for R in Rotation.random(200, random_state=1).as_matrix():
        q = _q(R)
        assert np.allclose(quat_to_matrix(q * rng.uniform(0.5, 2)), R, atol=1e-12)  # any norm
        assert np.allclose(quat_to_matrix(matrix_to_quat(R)), R, atol=1e-12)
    # near 180 degrees, where the trace branch fails
    R = Rotation.from_rotvec([np.pi - 1e-9, 0, 0]).as_matrix()
    assert np.allclose(quat_to_matrix(matrix_to_quat(R)), R, atol=1e-9)


def test_slerp_matches_scipy_and_takes_the_short_arc():
    rots = Rotation.random(2, random_state=3)
    ref = Slerp([0.0, 1.0], rots)
    q0, q1 = rots.as_quat()
    for u in (0.0, 0.1, 0.5, 0.93, 1.0):
        assert np.allclose(quat_to_matrix(slerp(q0, q1, u)), ref([u]).as_matrix()[0], atol=1e-12)
        # the same rotation with the opposite sign of quaternion gives the same answer
        assert np.allclose(quat_to_matrix(slerp(q0, -q1, u)), ref([u]).as_matrix()[0], atol=1e-12)
    assert np.allclose(slerp(q0, q0, 0.4), q0 / np.linalg.norm(q0))


def _tree(gap_s: float = 0.2) -> tuple[TfTree, list[np.ndarray]]:
    """map -> odom (dynamic, constant), odom -> base (dynamic, 10 Hz, turning and moving), base -> cam
    (static)."""
    t = TfTree(gap_s)
    m_o = rigid(Rotation.from_euler("z", 0.3).as_matrix(), [1.0, 2.0, 0.0])
    b_c = rigid(Rotation.from_euler("xyz", [-1.7, 0.1, -1.5]).as_matrix(), [0.1, 0.0, 1.2])
    t.add("map", "odom", 0, _q(m_o[:3, :3]), m_o[:3, 3], False)
    t.add("map", "odom", 10 * S, _q(m_o[:3, :3]), m_o[:3, 3], False)
    t.add("base", "cam", 0, _q(b_c[:3, :3]), b_c[:3, 3], True, "/tf_static")
    samples = []
    for k in range(11):
        T = rigid(Rotation.from_euler("z", 0.2 * k).as_matrix(), [0.5 * k, 0.1 * k * k, 0.0])
        samples.append(T)
        t.add("odom", "base", k * S // 10, _q(T[:3, :3]), T[:3, 3], False)
    return t, [m_o, b_c, *samples]


def test_lookup_composes_static_and_dynamic_and_interpolates():
    t, (m_o, b_c, *o_b) = _tree()
    # at a sample: exact composition
    T, why = t.lookup("map", "cam", 3 * S // 10)
    assert why == "" and np.allclose(T, m_o @ o_b[3] @ b_c, atol=1e-12)
    # between samples: translation linearly, rotation by slerp (scipy as the twin)
    u = 0.37
    s = int((0.3 + 0.1 * u) * S)
    rot = Slerp([0, 1], Rotation.from_matrix([o_b[3][:3, :3], o_b[4][:3, :3]]))([u]).as_matrix()[0]
    mid = rigid(rot, o_b[3][:3, 3] + u * (o_b[4][:3, 3] - o_b[3][:3, 3]))
    T, _ = t.lookup("map", "cam", s)
    assert np.allclose(T, m_o @ mid @ b_c, atol=1e-9)
    # the inverse direction, and a lookup up the tree only
    Ti, _ = t.lookup("cam", "map", s)
    assert np.allclose(Ti, invert(T), atol=1e-9)
    To, _ = t.lookup("odom", "cam", s)
    assert np.allclose(To, mid @ b_c, atol=1e-9)


def test_lookup_refuses_outside_and_across_gaps():
    t, _ = _tree(gap_s=0.15)
    assert t.lookup("map", "cam", -1)[1] == "outside"
    assert t.lookup("map", "cam", S + 1)[1] == "outside"
    t2 = TfTree(0.15)
    for k in (0, 1, 2, 6, 7, 8):  # samples at 0.0-0.2 s and 0.6-0.8 s: a 0.4 s dropout
        t2.add("odom", "base", k * S // 10, [0, 0, 0, 1], [k, 0, 0], False)
    assert t2.lookup("odom", "base", int(0.15 * S))[1] == ""
    assert t2.lookup("odom", "base", int(0.35 * S))[1] == "gap"
    # a transform published slowly (every 2 s, as some localisers publish map -> odom) has no gap
    t3 = TfTree(0.15)
    for k in range(4):
        t3.add("map", "odom", 2 * k * S, [0, 0, 0, 1], [k, 0, 0], False)
    T, why = t3.lookup("map", "odom", 3 * S)
    assert why == "" and np.allclose(T[:3, 3], [1.5, 0, 0])


def test_frames_not_connected_are_named_with_their_trees():
    t, _ = _tree()
    t.add("camera_link", "camera_optical_frame", 0, [0, 0, 0, 1], [0, 0, 0], True)
    with pytest.raises(ValidationError) as e:
        t.check_connected("map", "camera_optical_frame")
    msg = str(e.value)
    assert "not connected" in msg and "{base, cam, map, odom}" in msg
    assert "{camera_link, camera_optical_frame}" in msg
    with pytest.raises(ValidationError, match="'nowhere' is not in the recording's tf"):
        t.check_connected("map", "nowhere")


def test_clock_jump_and_two_parents_are_errors():
    t = TfTree(max_gap_s=1.0)
    t.add("odom", "base", 10 * S, [0, 0, 0, 1], [0, 0, 0], False)
    t.add("odom", "base", 10 * S - S // 2, [0, 0, 0, 1], [0, 0, 0], False)  # reordered: jitter, kept
    with pytest.raises(ValidationError, match="clock jump"):
        t.add("odom", "base", 5 * S, [0, 0, 0, 1], [0, 0, 0], False)
    with pytest.raises(ValidationError, match="two parents"):
        t.add("map", "base", 11 * S, [0, 0, 0, 1], [0, 0, 0], False)
    # samples that arrived out of order are sorted before interpolating
    T, why = t.lookup("odom", "base", 10 * S - S // 4)
    assert why == "" and np.allclose(T, np.eye(4))
