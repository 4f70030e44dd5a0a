"""COLMAP sparse models, text and binary, read without COLMAP itself.

Layout reference: COLMAP's documented output format (cameras, images, points3D in .txt or .bin).
Poses are world-to-camera (qvec wxyz, tvec), OpenCV axes, so they convert to fmgs Cameras directly.
"""

from __future__ import annotations

import importlib.util
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from fmgs.errors import ValidationError

# model id -> (name, number of parameters), as COLMAP numbers them.
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
MODEL_PARAMS = {name: n for name, n in CAMERA_MODELS.values()}
UNDISTORTED = ("SIMPLE_PINHOLE", "PINHOLE")


@dataclass
class ColmapCamera:
    id: int
    model: str
    width: int
    height: int
    params: list[float]

    @property
    def is_pinhole(self) -> bool:
        """True when no undistortion is needed (pinhole models, or radial ones with zero coefficients)."""
        if self.model in UNDISTORTED:
            return True
        k = 3 if self.model in ("SIMPLE_RADIAL", "RADIAL") else 4
        return self.model in ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV") and not any(self.params[k:])


@dataclass
class ColmapImage:
    id: int
    qvec: np.ndarray  # [4] wxyz, world-to-camera
    tvec: np.ndarray  # [3]
    camera_id: int
    name: str


@dataclass
class ColmapModel:
    cameras: dict[int, ColmapCamera]
    images: dict[int, ColmapImage]
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # [P,3] xyz
    colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), dtype=np.uint8))  # [P,3] rgb


Backend = Literal["auto", "pycolmap", "fmgs"]


def read_model(path: str | Path, backend: Backend = "fmgs") -> ColmapModel:
    """Read a COLMAP model folder (``cameras``, ``images``, ``points3D`` as .bin or .txt).

    ``backend``: "fmgs" parses the files here; "pycolmap" parses them with COLMAP's own reader and
    falls back to "fmgs" when pycolmap refuses the model (so a bad file gets our precise error);
    "auto" is "pycolmap" when it is importable, else "fmgs". Both give the same values, bit for bit,
    points in ascending point id. "fmgs" stays the default: pycolmap parses 300K points in ~0.3 s,
    but handing them to numpy one Python object at a time leaves it 1.1x faster than ours there and
    1.1x slower on a 26K-point model (benchmarks/colmap_read.py); and pycolmap 4.2.1 never returns
    from a truncated points3D.bin (still reading after 60 s; ours refuses it at once), so give it
    trusted files only.
    """
    path = Path(path)
    if backend not in ("auto", "pycolmap", "fmgs"):
        raise ValueError(f"unknown COLMAP reader backend {backend!r} (auto, pycolmap or fmgs)")
    if backend != "fmgs" and _has_model(path) and importlib.util.find_spec("pycolmap") is not None:
        try:
            return _read_pycolmap(path)
        except (RuntimeError, ValueError, IndexError):
            pass  # our reader names the file and the fault, or reads what pycolmap would not
    for ext, reader in ((".bin", _read_binary), (".txt", _read_text)):
        if _has_model(path, ext):
            try:
                return reader(path)
            except (struct.error, ValueError, IndexError, UnicodeDecodeError) as e:
                raise ValidationError(str(path), f"malformed COLMAP {ext[1:]} model ({e})") from e
    raise ValidationError(str(path), "no COLMAP model here (need cameras and images as .bin or .txt)")


def _has_model(path: Path, ext: str | None = None) -> bool:
    exts = (ext,) if ext else (".bin", ".txt")
    return any((path / f"cameras{e}").is_file() and (path / f"images{e}").is_file() for e in exts)


def _read_pycolmap(path: Path) -> ColmapModel:
    import pycolmap

    rec = pycolmap.Reconstruction(path)
    cameras = {
        cid: _check_camera(ColmapCamera(cid, c.model.name, c.width, c.height, c.params.tolist()))
        for cid, c in rec.cameras.items()
    }
    images = {}
    for iid, im in rec.images.items():
        if not im.has_pose:
            raise ValueError(f"image {iid} has no pose")  # our reader says what is wrong with it
        pose = im.cam_from_world()
        x, y, z, w = pose.rotation.quat  # Eigen order; the file's (w, x, y, z) unnormalised, bit for bit
        images[iid] = _check_image(
            ColmapImage(iid, np.array([w, x, y, z]), pose.translation.copy(), im.camera_id, im.name)
        )
    points = list(rec.points3D.items())
    return ColmapModel(
        cameras,
        images,
        *_points([i for i, _ in points], [p.xyz for _, p in points], [p.color for _, p in points]),
    )


def _check_camera(cam: ColmapCamera) -> ColmapCamera:
    want = MODEL_PARAMS.get(cam.model)
    if want is None:
        raise ValidationError("cameras", f"camera {cam.id}: unknown model {cam.model!r}")
    if len(cam.params) != want:
        raise ValidationError(
            "cameras", f"camera {cam.id}: {cam.model} takes {want} parameters, got {len(cam.params)}"
        )
    if not np.isfinite(cam.params).all() or cam.width < 1 or cam.height < 1:
        raise ValidationError("cameras", f"camera {cam.id}: non-finite parameters or empty size")
    return cam


def _check_image(img: ColmapImage) -> ColmapImage:
    if not (np.isfinite(img.qvec).all() and np.isfinite(img.tvec).all()) or not np.any(img.qvec):
        raise ValidationError("images", f"image {img.id} ({img.name}): non-finite or zero pose")
    return img


def _lines(path: Path):
    for line in path.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            yield line


def _read_text(path: Path) -> ColmapModel:
    cameras = {}
    for line in _lines(path / "cameras.txt"):
        p = line.split()
        cam = ColmapCamera(int(p[0]), p[1], int(p[2]), int(p[3]), [float(x) for x in p[4:]])
        cameras[cam.id] = _check_camera(cam)
    images = {}
    # images.txt holds two lines per image: the pose (10 fields, the last being the name, which may
    # contain spaces), then its 2D points (x y point3D_id triples; empty when it has none). The line after
    # a pose is its points line even when it looks like a pose (an integral first x), unless it is not
    # triples of numbers (files written without the empty lines); other lines are told apart by shape.
    after_pose = False
    for line in (path / "images.txt").read_text().splitlines():
        s = line.strip()
        if s.startswith("#"):
            continue
        if after_pose:
            after_pose = False
            if _is_points_line(s):
                continue
        if not s:
            continue
        p = s.split(maxsplit=9)
        if len(p) < 10 or not p[0].isdigit() or not p[8].lstrip("-").isdigit():
            continue  # a 2D-points line
        try:
            nums = [float(x) for x in p[1:8]]
        except ValueError:
            continue
        img = ColmapImage(int(p[0]), np.array(nums[:4]), np.array(nums[4:7]), int(p[8]), p[9])
        images[img.id] = _check_image(img)
        after_pose = True
    ids, pts, cols = [], [], []
    if (path / "points3D.txt").is_file():
        for line in _lines(path / "points3D.txt"):
            p = line.split()
            ids.append(int(p[0]))
            pts.append([float(x) for x in p[1:4]])
            cols.append([int(x) for x in p[4:7]])
    return ColmapModel(cameras, images, *_points(ids, pts, cols))


def _is_points_line(s: str) -> bool:
    """Whether an images.txt line is a 2D-points line: empty, or x y point3D_id triples of numbers."""
    fields = s.split()
    if len(fields) % 3:
        return False
    try:
        for x in fields:
            float(x)
    except ValueError:
        return False
    return True


def _points(ids: list[int], pts: list, cols: list) -> tuple[np.ndarray, np.ndarray]:
    """Finite points in ascending point id: one order whatever the file's order or the backend."""
    order = sorted(range(len(ids)), key=ids.__getitem__)  # exact for any id, where int64 may not be
    P = np.asarray(pts, dtype=np.float64).reshape(-1, 3)[order]
    C = np.asarray(cols, dtype=np.uint8).reshape(-1, 3)[order]
    keep = np.isfinite(P).all(1)
    return P[keep], C[keep]


class _Reader:
    def __init__(self, data: bytes) -> None:
        self.data, self.pos = data, 0

    def take(self, fmt: str):
        out = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += struct.calcsize("<" + fmt)
        return out

    def cstring(self) -> str:
        end = self.data.index(b"\0", self.pos)
        s = self.data[self.pos : end].decode("utf-8")
        self.pos = end + 1
        return s


def _read_binary(path: Path) -> ColmapModel:
    r = _Reader((path / "cameras.bin").read_bytes())
    cameras = {}
    for _ in range(r.take("Q")[0]):
        cid, mid, w, h = r.take("iiQQ")
        if mid not in CAMERA_MODELS:
            raise ValidationError("cameras", f"camera {cid}: unknown model id {mid}")
        name, n = CAMERA_MODELS[mid]
        cameras[cid] = _check_camera(ColmapCamera(cid, name, w, h, list(r.take(f"{n}d"))))
    r = _Reader((path / "images.bin").read_bytes())
    images = {}
    for _ in range(r.take("Q")[0]):
        iid, *pose, cid = r.take("i7di")
        name = r.cstring()
        n2d = r.take("Q")[0]
        r.pos += n2d * struct.calcsize("<ddq")
        images[iid] = _check_image(ColmapImage(iid, np.array(pose[:4]), np.array(pose[4:]), cid, name))
    ids, pts, cols = [], [], []
    if (path / "points3D.bin").is_file():
        r = _Reader((path / "points3D.bin").read_bytes())
        for _ in range(r.take("Q")[0]):
            pid, x, y, z, cr, cg, cb, _err = r.take("Q3d3Bd")
            track = r.take("Q")[0]
            r.pos += track * struct.calcsize("<ii")
            ids.append(pid)
            pts.append([x, y, z])
            cols.append([cr, cg, cb])
    return ColmapModel(cameras, images, *_points(ids, pts, cols))


def write_binary(model: ColmapModel, path: str | Path) -> None:
    """Write ``model`` as cameras.bin / images.bin / points3D.bin (no 2D observations or tracks)."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    ids = {name: mid for mid, (name, _) in CAMERA_MODELS.items()}
    out = [struct.pack("<Q", len(model.cameras))]
    for c in model.cameras.values():
        out.append(struct.pack(f"<iiQQ{len(c.params)}d", c.id, ids[c.model], c.width, c.height, *c.params))
    (path / "cameras.bin").write_bytes(b"".join(out))
    out = [struct.pack("<Q", len(model.images))]
    for im in model.images.values():
        out.append(struct.pack("<i7di", im.id, *im.qvec, *im.tvec, im.camera_id))
        out.append(im.name.encode() + b"\0" + struct.pack("<Q", 0))
    (path / "images.bin").write_bytes(b"".join(out))
    out = [struct.pack("<Q", len(model.points))]
    for i, (p, c) in enumerate(zip(model.points, model.colors, strict=True)):
        out.append(struct.pack("<Q3d3BdQ", i + 1, *p, *c, 0.0, 0))
    (path / "points3D.bin").write_bytes(b"".join(out))
