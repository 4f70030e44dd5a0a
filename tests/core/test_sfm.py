"""SfM: similarity alignment, pose errors, messages, and known intrinsics on six real photos (accuracy is
measured by benchmarks/sfm.py)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fmgs.errors import ValidationError
from fmgs.sfm import SfMConfig, align_similarity, completed_sfm, pose_errors, read_intrinsics, run_sfm


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


def test_photo_folder_messages_name_the_fix(tmp_path, capsys):
    from fmgs import cli

    assert cli.main(["sfm", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    assert "nope: does not exist" in capsys.readouterr().err
    (tmp_path / "images").mkdir()
    for i in range(3):
        (tmp_path / "images" / f"{i}.jpg").write_bytes(b"")
    assert cli.main(["sfm", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert f"photos are in {tmp_path / 'images'}: pass that" in capsys.readouterr().err


def test_camera_params_are_checked_against_the_model(tmp_path, capsys):
    from fmgs import cli

    with pytest.raises(ValueError, match=r"PINHOLE takes 4 values \(fx,fy,cx,cy\), got 3"):
        SfMConfig(camera_model="PINHOLE", camera_params=(400.0, 300.0, 200.0))
    argv = ["sfm", str(tmp_path), "--out", str(tmp_path / "o"), "--camera-params", "400,300,200"]
    assert cli.main(argv) == 2 and "PINHOLE" not in capsys.readouterr().err  # SIMPLE_RADIAL: f,cx,cy,k
    assert cli.main([*argv, "--camera-model", "PINHOLE"]) == 2
    assert "PINHOLE takes 4 values" in capsys.readouterr().err


def test_intrinsics_file_is_checked(tmp_path):
    f = tmp_path / "k.json"
    names = ["a.jpg", "b.jpg"]
    ok = {"model": "PINHOLE", "width": 40, "height": 30, "params": [50, 50, 20, 15]}
    f.write_text(json.dumps({"a.jpg": ok}))
    assert read_intrinsics(f, names) == {"a.jpg": ("PINHOLE", 40, 30, [50.0, 50.0, 20.0, 15.0])}
    for bad, msg in [
        ({"c.jpg": ok}, "no such photo"),
        ({"a.jpg": {**ok, "model": "FOO"}}, "unknown camera model 'FOO'"),
        ({"a.jpg": {**ok, "params": [1, 2]}}, "PINHOLE takes fx,fy,cx,cy, got 2"),
        ({"a.jpg": {"model": "PINHOLE"}}, "needs"),
    ]:
        f.write_text(json.dumps(bad))
        with pytest.raises(ValidationError, match=msg):
            read_intrinsics(f, names)


@pytest.fixture(scope="module")
def six_photos(tmp_path_factory, data_dir):
    """Six consecutive snowmiku photos (495x371) and the reference PINHOLE intrinsics."""
    import pycolmap

    src = data_dir / "snowmiku_small"
    d = tmp_path_factory.mktemp("photos")
    for n in sorted(p.name for p in (src / "images").iterdir())[:6]:
        shutil.copy(src / "images" / n, d / n)
    cam = next(iter(pycolmap.Reconstruction(src / "sparse/0").cameras.values()))
    return d, [float(v) for v in cam.params]


def test_known_intrinsics_are_held_and_colmap_logs_to_a_file(six_photos, tmp_path, capfd):
    """Shared camera_params: the reconstruction keeps them exactly (refine_known is off); COLMAP's log
    goes to OUT/colmap.log and the terminal gets the four phase lines only."""
    photos, known = six_photos
    res = run_sfm(photos, tmp_path, SfMConfig(camera_model="PINHOLE", camera_params=tuple(known)))
    assert res.registered == 6 and res.cameras == 1 and res.focal_source == "given"
    assert res.camera_model == "PINHOLE" and res.camera_params == pytest.approx(known, abs=1e-9)
    cap = capfd.readouterr()
    assert cap.out == "" and "sift" not in cap.err.lower()
    assert "Feature extraction" in (tmp_path / "colmap.log").read_text()
    # Its record lets a build reuse it for the same photos and settings only.
    cfg = SfMConfig(camera_model="PINHOLE", camera_params=tuple(known))
    assert completed_sfm(photos, tmp_path, cfg) == tmp_path / "undistorted"
    assert completed_sfm(photos, tmp_path, SfMConfig()) is None


def test_per_photo_intrinsics_file(six_photos, tmp_path):
    """Two photos listed with known OPENCV intrinsics (held), the rest estimated per photo (refined)."""
    photos, (fx, fy, cx, cy) = six_photos
    names = sorted(p.name for p in photos.iterdir())
    k = {"model": "OPENCV", "width": 495, "height": 371, "params": [fx, fy, cx, cy, 0, 0, 0, 0]}
    (tmp_path / "k.json").write_text(json.dumps({n: k for n in names[:2]}))
    res = run_sfm(photos, tmp_path / "out", SfMConfig(intrinsics_file=str(tmp_path / "k.json")))
    assert res.cameras == 6 and res.focal_source == "2 given, 4 default"
    assert res.camera_model == "OPENCV" and res.camera_params == pytest.approx(k["params"], abs=1e-9)
    again = run_sfm(
        photos, tmp_path / "refined", SfMConfig(intrinsics_file=str(tmp_path / "k.json"), refine_known=True)
    )
    assert again.camera_params != pytest.approx(k["params"], abs=1e-3)  # refine_known frees them
