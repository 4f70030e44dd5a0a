"""One posed-image dataset type for every entry point (COLMAP model or transforms.json)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fmgs.cameras import Camera
from fmgs.data import HOLDOUT_EVERY, IMAGE_SUFFIXES
from fmgs.data.colmap import read_model
from fmgs.data.transforms import parse_transforms
from fmgs.data.undistort import CACHE_DIR, fingerprint, undistorted_copy
from fmgs.errors import ValidationError
from fmgs.io.points import read_point_ply

log = logging.getLogger(__name__)


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

        An alpha channel (RGBA) is composited onto black; a 16-bit grey image is scaled by its full range.
        An image that does not decode raises ValidationError naming the file.
        """
        from PIL import Image

        f = self.frames[i]
        cam = f.camera.scaled(scale) if scale != 1.0 else f.camera
        try:
            with Image.open(f.image_path) as im:
                if im.size != (f.camera.width, f.camera.height):
                    raise ValidationError(
                        str(f.image_path),
                        f"image is {im.size[0]}x{im.size[1]}, camera says {f.camera.width}x{f.camera.height}",
                    )
                a = _pixels(im, (cam.width, cam.height), f.image_path)
        except OSError as e:  # PIL's UnidentifiedImageError and a truncated file's error are OSErrors
            raise ValidationError(str(f.image_path), f"cannot decode the image ({e})") from e
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


_GREY16 = ("I;16", "I;16L", "I;16B", "I;16N", "I")
"""PIL modes of 16-bit grey images (PNG, TIFF): converting them to RGB clips every value above 255."""


def _pixels(im, size: tuple[int, int], path: Path) -> np.ndarray:
    """An opened PIL image resized to ``size`` as float32 [H,W,3] (or [H,W,4] with alpha) in [0,1]."""
    from PIL import Image

    if im.mode in _GREY16:
        grey = im.convert("F")
        if grey.size != size:
            grey = grey.resize(size, Image.Resampling.LANCZOS)
        g = np.clip(np.asarray(grey, dtype=np.float32) / 65535.0, 0.0, 1.0)
        return np.repeat(g[..., None], 3, axis=-1)
    if im.mode == "F":
        raise ValidationError(str(path), "floating-point images are not supported: store 8- or 16-bit")
    im = im.convert("RGBA") if im.mode in ("RGBA", "LA", "P", "PA") else im.convert("RGB")
    if im.size != size:
        im = im.resize(size, Image.Resampling.LANCZOS)
    return np.asarray(im, dtype=np.float32) / 255.0


def load_dataset(path: str | Path, undistort_dir: str | Path | None = None) -> PosedDataset:
    """Read a dataset: a COLMAP model (``sparse/0``, ``sparse`` or the folder, images in ``images/``)
    or a ``transforms.json`` (instant-ngp, nerfstudio, Blender/NeRF-synthetic). When a folder has both,
    the COLMAP model wins: it carries sparse points.

    Cameras with lens distortion (either layout) are undistorted once by pycolmap into
    ``undistort_dir`` (default: ``fmgs_undistorted/`` beside the dataset) and read from there.
    """
    path = Path(path)
    if not path.exists():
        raise ValidationError(str(path), "no such file or folder")
    if path.is_file():
        if path.suffix == ".json":
            return read_transforms(path, undistort_dir)
        raise ValidationError(str(path), "expected a dataset folder or a transforms.json file")
    for sub in ("sparse/0", "sparse", "."):
        if (
            any((path / sub / f"cameras{e}").is_file() for e in (".bin", ".txt"))
            and (path / "images").is_dir()
        ):
            und = Path(undistort_dir) if undistort_dir is not None else path / CACHE_DIR
            return read_colmap(path / sub, path / "images", und)
    if (path / "transforms.json").is_file():
        return read_transforms(path / "transforms.json", undistort_dir)
    hint = ""
    if (path / "images").is_dir() or any(p.suffix.lower() in IMAGE_SUFFIXES for p in path.iterdir()):
        hint = "; photos without poses need `fmgs sfm` (or `fmgs build`, which runs it) first"
    raise ValidationError(
        str(path), f"no transforms.json and no COLMAP model (sparse/0, sparse or here){hint}"
    )


def read_colmap(
    model_dir: str | Path, image_dir: str | Path, undistort_dir: str | Path | None = None
) -> PosedDataset:
    """A dataset from a COLMAP model; distorted cameras are undistorted into ``undistort_dir`` or refused."""
    model_dir = Path(model_dir)
    model = read_model(model_dir)
    image_dir = Path(image_dir)
    if undistort_dir is not None and not all(c.is_pinhole for c in model.cameras.values()):
        files = [model_dir / f"{k}{e}" for k in ("cameras", "images") for e in (".bin", ".txt")]
        und = undistorted_copy(model, image_dir, Path(undistort_dir), fingerprint(files, str(image_dir)))
        return read_colmap(und / "sparse", und / "images")
    frames, missing = [], []
    for img in model.images.values():
        cam = model.cameras.get(img.camera_id)
        if cam is None:
            raise ValidationError("images", f"image {img.name} uses unknown camera {img.camera_id}")
        if not cam.is_pinhole:
            raise ValidationError(
                "cameras",
                f"camera {cam.id} is {cam.model} with distortion; undistort the model first "
                "(fmgs.data.undistort.undistorted_copy, or load_dataset with an undistort folder)",
            )
        p = image_dir / img.name
        if not p.is_file():
            missing.append(img.name)
            continue
        try:
            camera = Camera.from_colmap(
                img.qvec, img.tvec, cam.model, cam.params, cam.width, cam.height, name=img.name
            )
        except ValidationError as e:
            raise ValidationError(str(model_dir), f"image {img.name} (camera {cam.id}): {e}") from e
        frames.append(Frame(img.name, p, camera))
    _report_missing(str(model_dir), missing, len(model.images), image_dir)
    frames.sort(key=lambda f: f.name)
    return PosedDataset(model_dir, frames, model.points, model.colors)


def _report_missing(source: str, missing: list[str], total: int, where: Path) -> None:
    """One warning for all missing images; an error when none is left (or none is listed)."""
    if total == 0:
        raise ValidationError(source, "lists no images")
    if missing and len(missing) == total:
        raise ValidationError(
            source, f"none of its {total} images exists under {where} (first: {missing[0]})"
        )
    if missing:
        log.warning(
            "%s: %d of %d images are missing under %s and are skipped (first: %s)",
            source, len(missing), total, where, missing[0],
        )  # fmt: skip


def read_transforms(path: str | Path, undistort_dir: str | Path | None = None) -> PosedDataset:
    """A dataset from a ``transforms.json`` (OpenGL camera-to-world): instant-ngp, nerfstudio or
    Blender/NeRF-synthetic keys, global or per frame (``fmgs.data.transforms``). Frames whose image is
    missing are skipped (one warning with the count). Distorted cameras are undistorted into
    ``undistort_dir`` (default ``fmgs_undistorted/`` beside the file) and read from there."""
    path = Path(path)
    root = path.parent
    parsed = parse_transforms(path)
    _report_missing(str(path), parsed.missing, parsed.total, root)
    points = colors = None
    if parsed.ply_file:
        points, colors = read_point_ply(root / parsed.ply_file)
    if all(f.lens.is_pinhole for f in parsed.frames):
        frames = [Frame(f.name, f.image_path, f.camera) for f in parsed.frames]
        frames.sort(key=lambda f: f.name)
        return PosedDataset(root, frames, points, colors)
    und = Path(undistort_dir) if undistort_dir is not None else root / CACHE_DIR
    names = "\n".join(f.name for f in parsed.frames)
    copy = undistorted_copy(parsed.colmap_model(), root, und, fingerprint([path], names))
    ds = read_colmap(copy / "sparse", copy / "images")
    return PosedDataset(root, ds.frames, points, colors)
