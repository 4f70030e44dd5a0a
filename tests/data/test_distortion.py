"""Lens distortion: transforms.json keys, the one undistortion path (pycolmap, cached), checked against
an undistorted twin rendered by an independent renderer."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from fmgs.data.colmap import read_model
from fmgs.data.dataset import load_dataset
from fmgs.data.distortion import OpenCVDistortion
from fmgs.data.transforms import parse_transforms, rotmat_to_qvec
from fmgs.errors import ValidationError
from fmgs.metrics import psnr
from fmgs.synth import SynthConfig, generate

LENS = (-0.25, 0.08, 0.02, -0.015)  # k1, k2, p1, p2: a strong consumer wide-angle lens
SIZE = dict(views=2, width=128, height=96, points=500, objects=3)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("lens")
    generate(root / "twin", SynthConfig(**SIZE))
    generate(root / "distorted", SynthConfig(**SIZE, distortion=LENS))
    return {"twin": root / "twin", "distorted": root / "distorted", "root": root}


def test_undistort_inverts_distort():
    lens = OpenCVDistortion(*LENS, k3=0.01)
    x, y = np.meshgrid(np.linspace(-0.6, 0.6, 41), np.linspace(-0.45, 0.45, 31))
    xd, yd = lens.distort(x, y)
    assert np.abs(xd - x).max() > 0.02  # the lens does something
    xu, yu = lens.undistort(xd, yd)
    np.testing.assert_allclose(xu, x, atol=1e-12)
    np.testing.assert_allclose(yu, y, atol=1e-12)


def test_rotmat_to_qvec_round_trip():
    from fmgs.cameras import quat_wxyz_to_rotmat

    q = torch.randn(200, 4, dtype=torch.float64)
    q = q / q.norm(dim=1, keepdim=True)
    q = torch.where(q[:, :1] < 0, -q, q)
    R = quat_wxyz_to_rotmat(q).numpy()
    got = np.stack([rotmat_to_qvec(r) for r in R])
    np.testing.assert_allclose(got, q.numpy(), atol=1e-12)


def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sample [H,W,C] at pixel coordinates (centres at +0.5); also returns where all 4 taps exist."""
    H, W, _ = img.shape
    x, y = u - 0.5, v - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    ok = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < W) & (y0 + 1 < H)
    x0, y0 = np.clip(x0, 0, W - 2), np.clip(y0, 0, H - 2)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    top = img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx
    bottom = img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy, ok


def _psnr_vs_twin(ds, twin, i: int) -> float:
    """PSNR of an undistorted frame against the pinhole twin resampled to its camera (inner pixels)."""
    img, cam = ds.image(i)
    ref, cam0 = twin.image(i)
    jj, ii = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    u = cam0.fx * (jj - cam.cx) / cam.fx + cam0.cx
    v = cam0.fy * (ii - cam.cy) / cam.fy + cam0.cy
    s, ok = _bilinear(ref.numpy(), u, v)
    ok[:2], ok[-2:], ok[:, :2], ok[:, -2:] = False, False, False, False
    assert ok.mean() > 0.8
    return psnr(img[torch.from_numpy(ok)], torch.from_numpy(s[ok]))


def _variant(scenes, name: str, edit) -> Path:
    """A copy of the distorted dataset with its transforms.json edited (no undistorted cache)."""
    out = scenes["root"] / name
    shutil.copytree(scenes["distorted"], out, ignore=shutil.ignore_patterns("fmgs_undistorted"))
    meta = json.loads((out / "transforms.json").read_text())
    edit(meta)
    (out / "transforms.json").write_text(json.dumps(meta))
    return out


def test_distorted_transforms_are_undistorted_like_the_twin(scenes):
    twin = load_dataset(scenes["twin"])
    ds = load_dataset(scenes["distorted"])
    cache = scenes["distorted"] / "fmgs_undistorted"
    assert (cache / "source.json").is_file() and not list(scenes["distorted"].glob("*.tmp-*"))
    assert {c.model for c in read_model(cache / "sparse").cameras.values()} == {"PINHOLE"}
    assert [f.name for f in ds.frames] == [f.name for f in twin.frames]
    for a, b in zip(ds.frames, twin.frames, strict=True):  # undistortion keeps the poses
        torch.testing.assert_close(a.camera.viewmat, b.camera.viewmat, rtol=0, atol=1e-9)
    assert ds.points is not None and len(ds.points) == len(twin.points)
    good = [_psnr_vs_twin(ds, twin, i) for i in range(len(ds))]
    # Controls that must score worse: p1/p2 swapped, and the distortion ignored.
    swapped = load_dataset(_variant(scenes, "swapped", lambda m: m.update(p1=m["p2"], p2=m["p1"])))
    ignored = load_dataset(
        _variant(scenes, "ignored", lambda m: [m.pop(k) for k in ("k1", "k2", "p1", "p2", "camera_model")])
    )
    bad = [_psnr_vs_twin(d, twin, i) for d in (swapped, ignored) for i in range(len(ds))]
    assert min(good) >= 30.0, good  # measured 32.4-34.0 dB at 128x96
    assert max(bad) <= 28.0, bad  # measured 24.0-26.2 dB


def test_undistorted_copy_is_reused_and_rebuilt_when_the_source_changes(scenes, monkeypatch):
    import pycolmap

    load_dataset(scenes["distorted"])  # the copy exists (made here or by the test above)
    calls = []
    real = pycolmap.undistort_images
    monkeypatch.setattr(pycolmap, "undistort_images", lambda *a, **k: calls.append(a) or real(*a, **k))
    load_dataset(scenes["distorted"])
    assert calls == []
    changed = _variant(scenes, "changed", lambda m: m.update(k1=-0.2))
    shutil.copytree(scenes["distorted"] / "fmgs_undistorted", changed / "fmgs_undistorted")
    load_dataset(changed)
    assert len(calls) == 1

    def shape(d):
        c = d.frames[0].camera
        return (c.width, c.height, c.fx, c.fy, c.cx, c.cy)

    assert shape(load_dataset(changed)) != shape(load_dataset(scenes["distorted"]))


def test_fisheye_and_per_frame_lenses_map_to_colmap_models(tmp_path):
    from PIL import Image

    for n in ("a", "b", "c"):
        Image.new("RGB", (40, 30)).save(tmp_path / f"{n}.png")
    pose = np.eye(4).tolist()
    meta = {
        "fl_x": 30.0,
        "fl_y": 31.0,
        "w": 40,
        "h": 30,
        "frames": [
            {"file_path": "a.png", "transform_matrix": pose, "is_fisheye": True, "k1": 0.1, "k4": 0.01},
            {"file_path": "b.png", "transform_matrix": pose, "k1": 0.1, "k3": 0.02},
            {"file_path": "c", "transform_matrix": pose, "cx": 19.0},
            {"file_path": "gone.png", "transform_matrix": pose},
        ],
    }
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    parsed = parse_transforms(tmp_path / "transforms.json")
    assert parsed.missing == ["gone.png"] and parsed.total == 4
    lenses = {f.name: f.lens for f in parsed.frames}
    assert lenses["a.png"].model == "OPENCV_FISHEYE"
    assert lenses["a.png"].params == [30.0, 31.0, 20.0, 15.0, 0.1, 0.0, 0.0, 0.01]
    assert lenses["b.png"].model == "FULL_OPENCV" and lenses["b.png"].params[8] == 0.02
    assert lenses["c.png"].model == "PINHOLE" and lenses["c.png"].params == [30.0, 31.0, 19.0, 15.0]
    model = parsed.colmap_model()
    assert len(model.cameras) == 3 and len(model.images) == 3


@pytest.mark.parametrize(
    "edit, message",
    [
        ({"camera_model": "EQUIRECTANGULAR"}, "camera_model 'EQUIRECTANGULAR' is not supported"),
        ({"k4": 0.1}, "k4=0.1 on a perspective camera"),
        ({"k1": "abc"}, "k1 = 'abc' is not a finite number"),
        ({"is_fisheye": True, "p1": 0.01}, "a fisheye camera with tangential"),
        ({"fl_x": None}, "no focal length"),
    ],
)
def test_bad_lens_keys_are_named(tmp_path, edit, message):
    from PIL import Image

    Image.new("RGB", (40, 30)).save(tmp_path / "a.png")
    meta = {
        "fl_x": 30.0,
        "w": 40,
        "h": 30,
        "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}],
    }
    meta.update(edit)
    meta = {k: v for k, v in meta.items() if v is not None}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(ValidationError, match=f"transforms.json.*frame 0: {message}"):
        load_dataset(tmp_path)


def test_nerfstudio_phone_capture_loads_as_given(tmp_path):
    """A Polycam/Record3D-style nerfstudio export: per-frame intrinsics (each photo its own), OPENCV with
    zero coefficients, extra keys (applied_transform, depth_file_path, sharpness) ignored."""
    from PIL import Image

    (tmp_path / "images").mkdir()
    frames = []
    for k in range(3):
        Image.new("RGB", (64, 48), (40 * k, 20, 10)).save(tmp_path / "images" / f"frame_{k:05d}.jpg")
        c2w = np.eye(4)
        c2w[0, 3] = 0.1 * k
        frames.append(
            {
                "file_path": f"images/frame_{k:05d}.jpg",
                "depth_file_path": f"depth/{k}.png",
                "transform_matrix": c2w.tolist(),
                "fl_x": 50.0 + k,
                "fl_y": 50.5 + k,
                "cx": 31.0,
                "cy": 24.5,
                "w": 64,
                "h": 48,
                "sharpness": 12.0,
            }
        )
    meta = {"camera_model": "OPENCV", "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": frames}
    meta["applied_transform"] = np.eye(4)[:3].tolist()
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    ds = load_dataset(tmp_path)
    assert [f.name for f in ds.frames] == [f"images/frame_{k:05d}.jpg" for k in range(3)]
    assert [f.camera.fx for f in ds.frames] == [50.0, 51.0, 52.0]
    assert ds.frames[2].camera.fy == 52.5 and ds.frames[0].camera.cx == 31.0
    assert not (tmp_path / "fmgs_undistorted").exists()  # zero coefficients: nothing to resample
    torch.testing.assert_close(ds.frames[1].camera.center, torch.tensor([0.1, 0.0, 0.0], dtype=torch.float64))
