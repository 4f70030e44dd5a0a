"""Dataset readers: COLMAP text and binary, transforms.json, the held-out split."""

from __future__ import annotations

import json
import logging
import shutil

import numpy as np
import pytest
import torch

from fmgs.data.colmap import read_model, write_binary
from fmgs.data.dataset import load_dataset, read_colmap, read_transforms
from fmgs.errors import ValidationError


@pytest.fixture(scope="module")
def snow(data_dir):
    return data_dir / "snowmiku_small"


def test_colmap_text_model(snow):
    m = read_model(snow / "sparse/0")
    assert len(m.images) == 97 and len(m.cameras) == 1
    assert m.points.shape == (25_784, 3) and m.colors.dtype == np.uint8
    cam = next(iter(m.cameras.values()))
    assert cam.model == "PINHOLE" and (cam.width, cam.height) == (495, 371)


def test_colmap_binary_round_trip(snow, tmp_path):
    m = read_model(snow / "sparse/0")
    write_binary(m, tmp_path / "bin")
    b = read_model(tmp_path / "bin")
    assert b.cameras.keys() == m.cameras.keys() and b.images.keys() == m.images.keys()
    for i in m.images:
        assert b.images[i].name == m.images[i].name
        np.testing.assert_array_equal(b.images[i].qvec, m.images[i].qvec)
        np.testing.assert_array_equal(b.images[i].tvec, m.images[i].tvec)
    np.testing.assert_array_equal(b.points, m.points)
    np.testing.assert_array_equal(b.colors, m.colors)


def _assert_same_model(a, b) -> None:
    """Bit-for-bit: pycolmap keeps the file's quaternions unnormalised, so nothing needs a tolerance."""
    assert a.cameras.keys() == b.cameras.keys() and a.images.keys() == b.images.keys()
    for i, c in a.cameras.items():
        assert (c.id, c.model, c.width, c.height, c.params) == (
            b.cameras[i].id,
            b.cameras[i].model,
            b.cameras[i].width,
            b.cameras[i].height,
            b.cameras[i].params,
        )
    for i, im in a.images.items():
        assert (im.id, im.name, im.camera_id) == (b.images[i].id, b.images[i].name, b.images[i].camera_id)
        np.testing.assert_array_equal(im.qvec, b.images[i].qvec)
        np.testing.assert_array_equal(im.tvec, b.images[i].tvec)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.colors, b.colors)
    assert a.points.dtype == b.points.dtype and a.colors.dtype == b.colors.dtype


@pytest.mark.parametrize("form", ["text", "binary"])
def test_pycolmap_and_fmgs_readers_agree(snow, tmp_path, monkeypatch, form):
    pytest.importorskip("pycolmap")
    from fmgs.data import colmap

    path = snow / "sparse/0"
    if form == "binary":
        write_binary(read_model(path), tmp_path / "bin")
        path = tmp_path / "bin"
    ours = read_model(path, backend="fmgs")
    assert len(ours.images) == 97 and len(ours.points) == 25_784

    def no_fallback(_: object) -> None:
        raise AssertionError("pycolmap refused the model and our reader ran instead")

    monkeypatch.setattr(colmap, "_read_text", no_fallback)
    monkeypatch.setattr(colmap, "_read_binary", no_fallback)
    _assert_same_model(read_model(path, backend="pycolmap"), ours)
    _assert_same_model(read_model(path, backend="auto"), ours)


def test_points_come_in_point_id_order(tmp_path):
    """The file's order is not kept (pycolmap cannot keep it); non-finite points are dropped."""
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 10 10 5 5 5 5\n")
    (tmp_path / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n")
    (tmp_path / "points3D.txt").write_text("9 3 3 3 30 30 30 0\n2 1 1 1 10 10 10 0\n5 nan 0 0 1 1 1 0\n")
    for backend in ("fmgs", "pycolmap"):
        m = read_model(tmp_path, backend=backend)
        np.testing.assert_array_equal(m.points, [[1, 1, 1], [3, 3, 3]])
        np.testing.assert_array_equal(m.colors, [[10, 10, 10], [30, 30, 30]])


@pytest.mark.parametrize("backend", ["fmgs", "pycolmap", "auto"])
def test_bad_models_are_named_by_every_backend(tmp_path, backend):
    """pycolmap's refusals fall back to our reader, which names the file and the fault."""
    bad = tmp_path / "m"
    bad.mkdir()
    (bad / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n")
    for cams, fault in [
        ("1 PINHOLE 10 10 5 5\n", "takes 4 parameters"),
        ("1 WEIRD 10 10 5 5\n", "unknown model 'WEIRD'"),
        ("1 PINHOLE 10 0 5 5 5 5\n", "empty size"),
    ]:
        (bad / "cameras.txt").write_text(cams)
        with pytest.raises(ValidationError, match=rf"{bad}: malformed COLMAP txt model .*{fault}"):
            read_model(bad, backend=backend)
    (bad / "cameras.txt").write_text("1 PINHOLE 10 10 5 5 5 5\n")
    (bad / "images.txt").write_text("1 nan 0 0 0 0 0 0 1 a.png\n\n")
    with pytest.raises(ValidationError, match=r"non-finite or zero pose"):
        read_model(bad, backend=backend)
    # An unknown camera id: pycolmap refuses it, ours reads it (read_colmap names it later).
    (bad / "images.txt").write_text("1 1 0 0 0 0 0 0 7 a.png\n\n")
    assert read_model(bad, backend=backend).images[1].camera_id == 7
    with pytest.raises(ValidationError, match="no COLMAP model here"):
        read_model(tmp_path / "empty", backend=backend)
    with pytest.raises(ValueError, match="unknown COLMAP reader backend"):
        read_model(bad, backend="colmap")  # type: ignore[arg-type]


def test_colmap_and_transforms_datasets_agree(snow):
    a = read_transforms(snow / "transforms.json")
    c = load_dataset(snow)  # the COLMAP model wins when both exist: it has the sparse points
    assert len(a) == len(c) == 97
    for fa, fc in zip(a.frames, c.frames, strict=True):
        assert fa.image_path.name == fc.image_path.name
        assert torch.allclose(fa.camera.viewmat, fc.camera.viewmat, atol=1e-9)
    assert c.points is not None and a.points is None


def test_split_every_eighth(snow):
    ds = load_dataset(snow)
    train, test = ds.split()
    assert test == list(range(0, 97, 8)) and len(train) + len(test) == 97 and not set(train) & set(test)


def test_image_loading_and_scaling(snow):
    ds = load_dataset(snow)
    img, cam = ds.image(3)
    assert img.shape == (371, 495, 3) and img.dtype == torch.float32 and 0 <= img.min() and img.max() <= 1
    small, cam2 = ds.image(3, scale=0.25)
    assert small.shape == (cam2.height, cam2.width, 3) and cam2.fx == pytest.approx(cam.fx * cam2.width / 495)


def test_missing_images_are_skipped_with_a_warning(snow, tmp_path, caplog):
    meta = json.loads((snow / "transforms.json").read_text())
    (tmp_path / "images").mkdir()
    for fr in meta["frames"][:5]:
        shutil.copy(snow / fr["file_path"], tmp_path / fr["file_path"])
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with caplog.at_level(logging.WARNING):
        ds = read_transforms(tmp_path / "transforms.json")
    assert len(ds) == 5
    warned = [r.message for r in caplog.records if "missing" in r.message]
    assert len(warned) == 1 and "92 of 97 images are missing" in warned[0]  # one line, with the count


def test_camera_angle_and_extensionless_paths(snow, tmp_path):
    shutil.copy(snow / "images/20240212_003919.jpg", tmp_path / "r_0.jpg")
    meta = {"camera_angle_x": 0.9, "frames": [{"file_path": "./r_0", "transform_matrix": np.eye(4).tolist()}]}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    ds = read_transforms(tmp_path / "transforms.json")
    cam = ds.frames[0].camera
    assert (cam.width, cam.height) == (495, 371)
    assert cam.fx == pytest.approx(0.5 * 495 / np.tan(0.45))


def test_bad_inputs_are_named(tmp_path, snow):
    with pytest.raises(ValidationError, match=r"no transforms\.json and no COLMAP model"):
        load_dataset(tmp_path)
    (tmp_path / "transforms.json").write_text("{not json")
    with pytest.raises(ValidationError, match=r"cannot read transforms\.json"):
        load_dataset(tmp_path)
    bad = tmp_path / "m"
    bad.mkdir()
    (bad / "cameras.txt").write_text("1 OPENCV 10 10 5 5 5 5 0.1 0 0 0\n")
    (bad / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n")
    (tmp_path / "imgs").mkdir()
    with pytest.raises(ValidationError, match="undistort"):
        read_colmap(bad, tmp_path / "imgs")
    (bad / "cameras.txt").write_text("1 PINHOLE 10 10 5 5\n")
    with pytest.raises(ValidationError, match="takes 4 parameters"):
        read_model(bad)


def test_distorted_model_is_undistorted(snow, tmp_path):
    """An OPENCV camera with real distortion: refused without a folder, undistorted to PINHOLE with one."""
    from fmgs.data.colmap import ColmapCamera

    m = read_model(snow / "sparse/0")
    keep = dict(list(m.images.items())[:3])
    cam = next(iter(m.cameras.values()))
    fx, fy, cx, cy = cam.params
    m.cameras = {
        cam.id: ColmapCamera(cam.id, "OPENCV", cam.width, cam.height, [fx, fy, cx, cy, 0.05, 0.0, 0.0, 0.0])
    }
    m.images = keep
    write_binary(m, tmp_path / "model")
    with pytest.raises(ValidationError, match="undistort"):
        read_colmap(tmp_path / "model", snow / "images")
    ds = read_colmap(tmp_path / "model", snow / "images", undistort_dir=tmp_path / "und")
    assert len(ds) == 3 and (tmp_path / "und" / "images").is_dir()
    assert all(c.model == "PINHOLE" for c in read_model(tmp_path / "und" / "sparse").cameras.values())
    img, _ = ds.image(0)
    assert img.shape[-1] == 3 and float(img.std()) > 0.01


def _tiny_transforms(root, n=2, size=(8, 6), **top):
    """A transforms.json with ``n`` PNG frames of ``size`` at the identity pose (the images: mid grey)."""
    from PIL import Image

    (root / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(n):
        Image.new("RGB", size, (128, 128, 128)).save(root / "images" / f"{i}.png")
        frames.append({"file_path": f"images/{i}.png", "transform_matrix": np.eye(4).tolist()})
    meta = {"w": size[0], "h": size[1], "fl_x": 10.0, "fl_y": 10.0, **top, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    return meta


def test_sixteen_bit_grey_and_undecodable_images(tmp_path):
    """A 16-bit grey PNG keeps its values (converted to RGB it clipped to white); a file that does not
    decode is named, not a PIL traceback."""
    from PIL import Image

    _tiny_transforms(tmp_path, n=3)
    grey = np.full((6, 8), 0.25 * 65535, dtype=np.uint16)
    Image.fromarray(grey).save(tmp_path / "images" / "0.png")
    assert Image.open(tmp_path / "images" / "0.png").mode.startswith("I")
    (tmp_path / "images" / "1.png").write_bytes(b"not an image")
    good = (tmp_path / "images" / "2.png").read_bytes()
    ds = read_transforms(tmp_path / "transforms.json")
    img, _ = ds.image(0)
    assert img.shape == (6, 8, 3) and torch.allclose(img, torch.full_like(img, 0.25), atol=1e-4)
    small, cam = ds.image(0, scale=0.5)
    assert small.shape == (cam.height, cam.width, 3) and torch.allclose(
        small, torch.full_like(small, 0.25), atol=1e-3
    )
    with pytest.raises(ValidationError, match=r"1\.png: cannot decode the image"):
        ds.image(1)
    (tmp_path / "images" / "2.png").write_bytes(good[: len(good) // 2])
    with pytest.raises(ValidationError, match=r"2\.png: cannot decode the image"):
        ds.image(2)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda m: m.update(camera_angle_x=0.0, fl_x=None), r"camera_angle_x = 0\.0 is not a field of view"),
        (
            lambda m: m.update(camera_angle_y=-0.5, fl_y=None),
            r"camera_angle_y = -0\.5 is not a field of view",
        ),
        (lambda m: m.update(frames=[]), r"transforms\.json: lists no images"),
        (lambda m: m.update(ply_file_path="absent.ply"), r"absent\.ply: not a readable point PLY"),
    ],
)
def test_bad_transforms_are_named(tmp_path, edit, message):
    """A zero field of view divided by zero, an empty frame list ran to a misleading error at the field
    stage, a missing point file was a FileNotFoundError."""
    meta = _tiny_transforms(tmp_path)
    edit(meta)
    meta = {k: v for k, v in meta.items() if v is not None}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(ValidationError, match=message):
        load_dataset(tmp_path)


def test_point_files_drop_non_finite_points(tmp_path):
    from fmgs.io.points import write_point_ply

    _tiny_transforms(tmp_path, ply_file_path="points.ply")
    pts = np.array([[0.0, 0, 1], [np.nan, 0, 1], [1, np.inf, 1], [1, 1, 1]])
    write_point_ply(tmp_path / "points.ply", pts, np.arange(12, dtype=np.uint8).reshape(4, 3))
    ds = load_dataset(tmp_path)
    np.testing.assert_array_equal(ds.points, pts[[0, 3]])
    np.testing.assert_array_equal(ds.colors, [[0, 1, 2], [9, 10, 11]])


@pytest.mark.parametrize("backend", ["fmgs", "pycolmap"])
def test_a_points_line_with_an_integral_first_x_is_not_an_image(tmp_path, backend):
    """images.txt's 2D-points line '2 4 -1 ...' has the shape of a pose line of image 2: read as one, it
    replaced image 2 (b.png) with a bogus image named '2 2 -1' of camera -1."""
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 10 10 5 5 5 5\n")
    (tmp_path / "images.txt").write_text(
        "# Image list\n"
        "2 1 0 0 0 0 0 0 1 b.png\n3 4 -1 5.5 5.5 7 6 6 -1 2 2 -1\n"
        "1 1 0 0 0 1 0 0 1 a.png\n2 4 -1 5.5 5.5 7 6 6 -1 2 2 -1\n"
    )
    m = read_model(tmp_path, backend=backend)
    assert {i: (im.name, im.camera_id) for i, im in m.images.items()} == {2: ("b.png", 1), 1: ("a.png", 1)}
    # Files without the (empty) points lines still read.
    (tmp_path / "images.txt").write_text("2 1 0 0 0 0 0 0 1 b.png\n1 1 0 0 0 1 0 0 1 a.png\n")
    assert sorted(im.name for im in read_model(tmp_path, backend=backend).images.values()) == [
        "a.png",
        "b.png",
    ]


def test_a_zero_focal_length_names_the_model_and_image(tmp_path):
    (tmp_path / "sparse").mkdir()
    (tmp_path / "sparse" / "cameras.txt").write_text("1 PINHOLE 8 6 0 10 4 3\n")
    (tmp_path / "sparse" / "images.txt").write_text("1 1 0 0 0 0 0 0 1 0.png\n\n")
    _tiny_transforms(tmp_path, n=1)
    with pytest.raises(ValidationError, match=r"sparse: image 0\.png \(camera 1\): K: focal lengths"):
        load_dataset(tmp_path)
