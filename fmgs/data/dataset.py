"""One posed-image dataset type for every entry point (COLMAP model or transforms.json)."""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fmgs.cameras import Camera
from fmgs.data import HOLDOUT_EVERY
from fmgs.data.colmap import read_model
from fmgs.errors import ValidationError

log = logging.getLogger(__name__)

# Photo file extensions we read (compared case-insensitively).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


@dataclass(frozen=True)
class Frame:
    """One posed image."""

    name: str
    """Image file name relative to the dataset's image folder."""
    image_path: Path
    """Where the image file lies."""
    camera: Camera
    """Pinhole camera at the image's full resolution."""


@dataclass
class PosedDataset:
    """Posed images of one scene, frames sorted by name, with optional sparse points."""

    root: Path
    """The folder the dataset was read from."""
    frames: list[Frame]
    """Every usable frame, sorted by name."""
    points: np.ndarray | None = None
    """[P,3] float64 sparse points (SfM), or None."""
    colors: np.ndarray | None = None
    """[P,3] uint8 colours of the points, or None."""

    def __len__(self) -> int:
        return len(self.frames)

    def split(self, holdout_every: int = HOLDOUT_EVERY) -> tuple[list[int], list[int]]:
        """(train, held-out) frame indices: every ``holdout_every``-th frame (0, 8, 16, ...) is held out."""
        if holdout_every < 2:
            return list(range(len(self.frames))), []
        test = [i for i in range(len(self.frames)) if i % holdout_every == 0]
        return [i for i in range(len(self.frames)) if i % holdout_every != 0], test

    def image(self, i: int, scale: float = 1.0) -> tuple[torch.Tensor, Camera]:
        """Frame i as float32 RGB [H,W,3] in [0,1], resized by ``scale``, with the matching camera.

        An alpha channel (RGBA) is composited onto black.
        """
        from PIL import Image

        f = self.frames[i]
        cam = f.camera.scaled(scale) if scale != 1.0 else f.camera
        with Image.open(f.image_path) as im:
            if im.size != (f.camera.width, f.camera.height):
                raise ValidationError(
                    str(f.image_path),
                    f"image is {im.size[0]}x{im.size[1]}, camera says {f.camera.width}x{f.camera.height}",
                )
            im = im.convert("RGBA") if im.mode in ("RGBA", "LA", "P") else im.convert("RGB")
            if (cam.width, cam.height) != im.size:
                im = im.resize((cam.width, cam.height), Image.Resampling.LANCZOS)
            a = np.asarray(im, dtype=np.float32) / 255.0
        if a.shape[-1] == 4:
            a = a[..., :3] * a[..., 3:]
        return torch.from_numpy(np.ascontiguousarray(a)), cam

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned box of the sparse points (or of the camera centres when there are none)."""
        if self.points is not None and len(self.points):
            pts = self.points
        else:
            pts = np.stack([f.camera.center.numpy() for f in self.frames])
        return pts.min(0), pts.max(0)


def load_dataset(path: str | Path, undistort_dir: str | Path | None = None) -> PosedDataset:
    """Read a dataset: a COLMAP model (``sparse/0``, ``sparse`` or the folder, images in ``images/``)
    or ``transforms.json``. When a folder has both, the COLMAP model wins: it carries sparse points.

    A COLMAP model with distorted cameras is undistorted (pycolmap) into ``undistort_dir`` first;
    an existing undistorted copy there is reused.
    """
    path = Path(path)
    if path.is_file() and path.name.endswith(".json"):
        return read_transforms(path)
    for sub in ("sparse/0", "sparse", "."):
        if (
            any((path / sub / f"cameras{e}").is_file() for e in (".bin", ".txt"))
            and (path / "images").is_dir()
        ):
            return read_colmap(path / sub, path / "images", undistort_dir)
    if (path / "transforms.json").is_file():
        return read_transforms(path / "transforms.json")
    raise ValidationError(str(path), "no transforms.json and no COLMAP model (sparse/0, sparse or here)")


def read_colmap(
    model_dir: str | Path, image_dir: str | Path, undistort_dir: str | Path | None = None
) -> PosedDataset:
    """A dataset from a COLMAP model; distorted cameras are undistorted into ``undistort_dir`` or refused."""
    model = read_model(model_dir)
    image_dir = Path(image_dir)
    if undistort_dir is not None and not all(c.is_pinhole for c in model.cameras.values()):
        und = Path(undistort_dir)
        if not (und / "sparse" / "cameras.bin").is_file():
            undistort_colmap(model_dir, image_dir, und)
        return read_colmap(und / "sparse", und / "images")
    frames = []
    for img in model.images.values():
        cam = model.cameras.get(img.camera_id)
        if cam is None:
            raise ValidationError("images", f"image {img.name} uses unknown camera {img.camera_id}")
        if not cam.is_pinhole:
            raise ValidationError(
                "cameras",
                f"camera {cam.id} is {cam.model} with distortion; undistort the model first "
                "(fmgs.data.undistort.undistort_colmap or `fmgs sfm`)",
            )
        p = image_dir / img.name
        if not p.is_file():
            log.warning("skipping %s: image file missing", p)
            continue
        frames.append(
            Frame(
                img.name,
                p,
                Camera.from_colmap(
                    img.qvec, img.tvec, cam.model, cam.params, cam.width, cam.height, name=img.name
                ),
            )
        )
    if not frames:
        raise ValidationError(str(image_dir), "no image of the COLMAP model was found")
    frames.sort(key=lambda f: f.name)
    return PosedDataset(Path(model_dir), frames, model.points, model.colors)


def undistort_colmap(model_dir: str | Path, image_dir: str | Path, out: str | Path) -> Path:
    """Undistort a COLMAP model and its images to PINHOLE with pycolmap; writes out/{images, sparse}."""
    import pycolmap

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    pycolmap.undistort_images(out, Path(model_dir), Path(image_dir))
    if not (out / "sparse" / "cameras.bin").is_file():
        raise ValidationError(str(out), "undistortion wrote no model")
    return out


def read_transforms(path: str | Path) -> PosedDataset:
    """A dataset from an instant-ngp / nerfstudio ``transforms.json`` (OpenGL camera-to-world).

    Intrinsics may be global or per frame (fl_x/fl_y/cx/cy/w/h, or camera_angle_x); frames whose
    image is missing are skipped with a warning. Non-zero distortion coefficients are refused.
    """
    path = Path(path)
    try:
        meta = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValidationError(str(path), f"cannot read transforms.json ({e})") from e
    if not isinstance(meta.get("frames"), list):
        raise ValidationError(str(path), "no 'frames' list")
    root = path.parent
    frames = []
    for i, fr in enumerate(meta["frames"]):
        p = _resolve_image(root, str(fr.get("file_path", "")))
        if p is None:
            log.warning("skipping frame %d: image %s missing", i, fr.get("file_path"))
            continue
        get = lambda k, fr=fr: fr.get(k, meta.get(k))  # noqa: E731 (per-frame value overrides global)
        w, h = get("w"), get("h")
        if w is None or h is None:
            from PIL import Image

            with Image.open(p) as im:
                w, h = im.size
        fx, fy = get("fl_x"), get("fl_y")
        if fx is None:
            angle = get("camera_angle_x")
            if angle is None:
                raise ValidationError(str(path), f"frame {i}: no focal length (fl_x or camera_angle_x)")
            fx = 0.5 * w / math.tan(0.5 * float(angle))
        if fy is None:
            angle_y = get("camera_angle_y")
            fy = 0.5 * h / math.tan(0.5 * float(angle_y)) if angle_y is not None else fx
        cx, cy = get("cx"), get("cy")
        cx = w / 2 if cx is None else cx
        cy = h / 2 if cy is None else cy
        dist = [get(k) or 0.0 for k in ("k1", "k2", "k3", "k4", "p1", "p2")]
        if any(dist):
            raise ValidationError(
                str(path), f"frame {i}: distortion {dist} is not supported; undistort first"
            )
        try:
            c2w = torch.tensor(fr["transform_matrix"], dtype=torch.float64)
            cam = Camera.from_opengl_c2w(
                c2w, Camera.intrinsics(fx, fy, cx, cy), int(w), int(h), name=str(p.relative_to(root))
            )
        except (KeyError, TypeError, ValueError, RuntimeError) as e:
            raise ValidationError(str(path), f"frame {i}: bad transform_matrix or intrinsics ({e})") from e
        frames.append(Frame(str(p.relative_to(root)), p, cam))
    if not frames:
        raise ValidationError(str(path), "none of the listed images exist")
    frames.sort(key=lambda f: f.name)
    points = colors = None
    if meta.get("ply_file_path"):
        points, colors = _read_point_ply(root / meta["ply_file_path"])
    return PosedDataset(root, frames, points, colors)


def _resolve_image(root: Path, file_path: str) -> Path | None:
    p = root / file_path
    if p.is_file():
        return p
    for suf in IMAGE_SUFFIXES:  # NeRF-synthetic style paths omit the extension
        for cased in (suf, suf.upper()):
            q = p.with_name(p.name + cased)
            if q.is_file():
                return q
    return None


def _read_point_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    from plyfile import PlyData

    v = PlyData.read(str(path))["vertex"]
    pts = np.stack([np.asarray(v[k], dtype=np.float64) for k in ("x", "y", "z")], 1)
    names = {p.name for p in v.properties}
    if {"red", "green", "blue"} <= names:
        cols = np.stack([np.asarray(v[k]) for k in ("red", "green", "blue")], 1).astype(np.uint8)
    else:
        cols = np.full((len(pts), 3), 128, dtype=np.uint8)
    return pts, cols
