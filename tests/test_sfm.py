"""SfM helpers: similarity alignment and pose errors (the pycolmap run is in benchmarks/sfm.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fmgs.errors import ValidationError
from fmgs.sfm import align_similarity, pose_errors, run_sfm


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    R = Rotation.random(random_state=1).as_matrix()
    dst = 2.5 * src @ R.T + np.array([1.0, -2.0, 0.5])
    s, R2, t = align_similarity(src, dst)
    assert s == pytest.approx(2.5) and np.allclose(R2, R) and np.allclose(t, [1.0, -2.0, 0.5])


def test_pose_errors_are_zero_for_a_similar_copy_and_see_a_perturbation():
    rng = np.random.default_rng(2)
    ref = []
    for _ in range(10):
        V = np.eye(4)
        V[:3, :3] = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        V[:3, 3] = rng.normal(size=3) * 3
        ref.append(V)
    # The same cameras in a world scaled by 0.3, rotated and shifted (what SfM returns).
    S, Rw, tw = 0.3, Rotation.random(random_state=5).as_matrix(), np.array([4.0, 0.0, -1.0])
    est = []
    for V in ref:
        c = -V[:3, :3].T @ V[:3, 3]
        c2 = S * Rw @ c + tw
        E = np.eye(4)
        E[:3, :3] = V[:3, :3] @ Rw.T
        E[:3, 3] = -E[:3, :3] @ c2
        est.append(E)
    err = pose_errors(est, ref)
    assert max(err.rotation_deg) < 1e-6 and max(err.centre_rel) < 1e-9 and err.scale == pytest.approx(1 / S)
    c3 = -est[3][:3, :3].T @ est[3][:3, 3]  # turn camera 3 by 2 degrees about its own centre
    est[3] = est[3].copy()
    est[3][:3, :3] = Rotation.from_euler("z", 2.0, degrees=True).as_matrix() @ est[3][:3, :3]
    est[3][:3, 3] = -est[3][:3, :3] @ c3
    assert pose_errors(est, ref).rotation_deg[3] == pytest.approx(2.0, abs=1e-6)


def test_run_sfm_rejects_too_few_photos(tmp_path):
    with pytest.raises(ValidationError, match="at least 3 photos"):
        run_sfm(tmp_path, tmp_path / "out")
