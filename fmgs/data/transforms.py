"""``transforms.json`` parsing: instant-ngp, nerfstudio and Blender/NeRF-synthetic conventions.

Keys are read per frame, falling back to the file's top level:

- size ``w``, ``h`` (else read from the image); focal ``fl_x``/``fl_y`` or ``camera_angle_x``/``_y``;
  principal point ``cx``, ``cy`` (default: the image centre);
- distortion ``k1 k2 k3 k4 p1 p2``; ``camera_model`` (nerfstudio: PINHOLE, SIMPLE_PINHOLE, OPENCV,
  OPENCV_FISHEYE) or ``is_fisheye`` (instant-ngp). Perspective lenses map to COLMAP's OPENCV
  (FULL_OPENCV when k3 is set), fisheye ones to OPENCV_FISHEYE (k1..k4);
- ``transform_matrix``: OpenGL camera-to-world, 4x4 or 3x4; ``ply_file_path``: sparse points.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fmgs.cameras import Camera
from fmgs.data import IMAGE_SUFFIXES
from fmgs.data.colmap import ColmapCamera, ColmapImage, ColmapModel
from fmgs.errors import ValidationError

CAMERA_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "OPENCV_FISHEYE")
"""``camera_model`` values we read (nerfstudio's names)."""
_DIST_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


@dataclass
class TransformsFrame:
    """One frame whose image exists."""

    name: str
    """Image path relative to the file's folder (with its extension), or the listed file_path."""
    image_path: Path | None
    """None only for frames without an image, kept on request (camera paths)."""
    camera: Camera
    """Pose and the pinhole part of the intrinsics."""
    lens: ColmapCamera
    """The full camera as a COLMAP model (PINHOLE, OPENCV, FULL_OPENCV or OPENCV_FISHEYE)."""


@dataclass
class ParsedTransforms:
    frames: list[TransformsFrame]
    missing: list[str]
    """file_path of the frames without an image."""
    total: int
    """Frames listed."""
    ply_file: str | None
    """Sparse points (``ply_file_path``), relative to the file's folder."""

    def colmap_model(self) -> ColmapModel:
        """The frames as a COLMAP model (cameras shared where identical), for pycolmap's undistortion."""
        cameras: dict[tuple, ColmapCamera] = {}
        images = {}
        for i, f in enumerate(self.frames, start=1):
            key = (f.lens.model, f.lens.width, f.lens.height, *f.lens.params)
            if key not in cameras:
                c = f.lens
                cameras[key] = ColmapCamera(len(cameras) + 1, c.model, c.width, c.height, list(c.params))
            V = f.camera.viewmat.numpy()
            images[i] = ColmapImage(i, rotmat_to_qvec(V[:3, :3]), V[:3, 3].copy(), cameras[key].id, f.name)
        cams = {c.id: c for c in cameras.values()}
        return ColmapModel(cams, images, np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8))


def parse_transforms(path: Path, keep_missing: bool = False) -> ParsedTransforms:
    """Read ``path``; ValidationError naming the file, the frame and the key for anything malformed.

    Frames whose image is missing are listed in ``missing`` and dropped, or kept with
    ``image_path=None`` when ``keep_missing`` (a camera path to render; their size must be given)."""
    try:
        meta = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValidationError(str(path), f"cannot read transforms.json ({e})") from e
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise ValidationError(str(path), "no 'frames' list")
    root = path.parent
    frames, missing = [], []
    for i, fr in enumerate(meta["frames"]):
        if not isinstance(fr, dict):
            raise ValidationError(str(path), f"frame {i} is not an object")
        p = resolve_image(root, str(fr.get("file_path", "")))
        if p is None:
            missing.append(str(fr.get("file_path")))
            if not keep_missing:
                continue
        name = p.relative_to(root).as_posix() if p is not None else str(fr.get("file_path"))
        lens = _lens(path, i, fr, meta, p)
        fx, fy, cx, cy = lens.params[:4]
        try:
            cam = Camera.from_opengl_c2w(
                torch.tensor(fr["transform_matrix"], dtype=torch.float64),
                Camera.intrinsics(fx, fy, cx, cy), lens.width, lens.height, name=name,
            )  # fmt: skip
        except KeyError as e:
            raise ValidationError(str(path), f"frame {i}: no transform_matrix") from e
        except (TypeError, ValueError, RuntimeError) as e:
            raise ValidationError(str(path), f"frame {i}: bad transform_matrix or intrinsics ({e})") from e
        frames.append(TransformsFrame(name, p, cam, lens))
    ply = meta.get("ply_file_path")
    return ParsedTransforms(frames, missing, len(meta["frames"]), str(ply) if ply else None)


def _lens(path: Path, i: int, fr: dict, meta: dict, image: Path | None) -> ColmapCamera:
    """The frame's camera (per-frame keys override the file's) as a COLMAP camera model."""

    def get(key):
        return fr.get(key, meta.get(key))

    def num(key, default=None) -> float:
        v = get(key)
        if v is None:
            return default
        try:
            x = float(v)
        except (TypeError, ValueError):
            x = math.nan
        if not math.isfinite(x):
            raise ValidationError(str(path), f"frame {i}: {key} = {v!r} is not a finite number")
        return x

    w, h = get("w"), get("h")
    if w is None or h is None:  # Blender/NeRF-synthetic files give no size: read it from the image
        if image is None:
            raise ValidationError(str(path), f"frame {i}: no image to read its size from; give w and h")
        from PIL import Image

        try:
            with Image.open(image) as im:
                w, h = im.size
        except OSError as e:
            raise ValidationError(str(image), f"cannot read the image's size ({e})") from e
    w, h = int(num("w", w)), int(num("h", h))

    def angle(key) -> float | None:
        a = num(key)
        if a is not None and not 0.0 < a < math.pi:
            raise ValidationError(str(path), f"frame {i}: {key} = {a} is not a field of view in (0, pi)")
        return a

    fx = num("fl_x")
    if fx is None:
        angle_x = angle("camera_angle_x")
        if angle_x is None:
            raise ValidationError(str(path), f"frame {i}: no focal length (fl_x or camera_angle_x)")
        fx = 0.5 * w / math.tan(0.5 * angle_x)
    fy = num("fl_y")
    if fy is None:
        angle_y = angle("camera_angle_y")
        fy = 0.5 * h / math.tan(0.5 * angle_y) if angle_y is not None else fx
    cx, cy = num("cx", w / 2), num("cy", h / 2)
    k1, k2, k3, k4, p1, p2 = (num(k, 0.0) for k in _DIST_KEYS)
    model = get("camera_model")
    fisheye = bool(get("is_fisheye")) or model == "OPENCV_FISHEYE"
    if model is not None and model not in CAMERA_MODELS:
        raise ValidationError(
            str(path), f"frame {i}: camera_model {model!r} is not supported; supported: {CAMERA_MODELS}"
        )
    if fisheye:
        if p1 or p2:
            raise ValidationError(
                str(path), f"frame {i}: a fisheye camera with tangential p1={p1}, p2={p2} has no COLMAP model"
            )
        return ColmapCamera(0, "OPENCV_FISHEYE", w, h, [fx, fy, cx, cy, k1, k2, k3, k4])
    if k4:
        raise ValidationError(
            str(path), f"frame {i}: k4={k4} on a perspective camera (k4 is a fisheye coefficient)"
        )
    if k3:
        return ColmapCamera(0, "FULL_OPENCV", w, h, [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0])
    if k1 or k2 or p1 or p2:
        return ColmapCamera(0, "OPENCV", w, h, [fx, fy, cx, cy, k1, k2, p1, p2])
    return ColmapCamera(0, "PINHOLE", w, h, [fx, fy, cx, cy])


def resolve_image(root: Path, file_path: str) -> Path | None:
    """The image a frame's ``file_path`` names; NeRF-synthetic style paths omit the extension."""
    p = root / file_path
    if p.is_file():
        return p
    for suf in IMAGE_SUFFIXES:
        for cased in (suf, suf.upper()):
            q = p.with_name(p.name + cased)
            if q.is_file():
                return q
    return None


def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """[4] unit quaternion wxyz (w >= 0) of a [3,3] rotation matrix (Shepperd's method, stable)."""
    tr = np.trace(R)
    i = int(np.argmax([tr, R[0, 0], R[1, 1], R[2, 2]]))
    if i == 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif i == 1:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif i == 2:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    return -q if q[0] < 0 else q
