"""Undistorted copies of datasets with lens distortion, made once by pycolmap and cached.

COLMAP models with distorted cameras and ``transforms.json`` files with distortion keys both come here
as a COLMAP model: one code path undistorts them to PINHOLE (images resampled, intrinsics replaced;
poses unchanged). The copy lies in ``fmgs_undistorted/`` beside the dataset unless a folder is given,
carries the fingerprint of its source, is rebuilt when the source changes and is swapped in whole, so a
reader never sees a half-written copy.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from pathlib import Path

from fmgs.data.colmap import ColmapModel, write_binary
from fmgs.errors import ValidationError
from fmgs.io.capture import output_to

log = logging.getLogger(__name__)

CACHE_DIR = "fmgs_undistorted"
"""Default folder of the undistorted copy, beside the dataset."""
_SOURCE = "source.json"


def fingerprint(files: list[Path], extra: str = "") -> str:
    """sha256 over the bytes of ``files`` (missing ones count as empty) and ``extra``."""
    h = hashlib.sha256(extra.encode())
    for f in files:
        h.update(f.name.encode() + b"\0")
        h.update(f.read_bytes() if f.is_file() else b"")
    return h.hexdigest()


def undistorted_copy(model: ColmapModel, image_dir: Path, out: Path, source_fingerprint: str) -> Path:
    """Undistort ``model`` (distorted cameras, images under ``image_dir``) into ``out``/{images, sparse}.

    An existing copy made from the same source is reused. Raises ValidationError when ``out`` cannot
    be written (name the folder to use instead) or pycolmap produces no model.
    """
    out = Path(out)
    try:
        if json.loads((out / _SOURCE).read_text()).get("fingerprint") == source_fingerprint:
            return out
    except (OSError, ValueError):
        pass
    import pycolmap

    tmp = out.with_name(f"{out.name}.tmp-{os.getpid()}")
    try:
        shutil.rmtree(tmp, ignore_errors=True)
        write_binary(model, tmp / "distorted")
        n = len(model.images)
        log.info("undistorting %d images into %s (once; reused while the dataset is unchanged)", n, out)
        tmp.mkdir(parents=True, exist_ok=True)
        with output_to(tmp / "colmap.log"):  # pycolmap's own log lines stay off the terminal
            pycolmap.undistort_images(tmp, tmp / "distorted", image_dir)
        if not (tmp / "sparse" / "cameras.bin").is_file():
            raise ValidationError(str(out), "pycolmap's undistortion wrote no model")
        shutil.rmtree(tmp / "distorted")
        (tmp / _SOURCE).write_text(json.dumps({"fingerprint": source_fingerprint, "images": n}))
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    except OSError as e:
        shutil.rmtree(tmp, ignore_errors=True)
        raise ValidationError(
            str(out), f"cannot write the undistorted copy here ({e}); pass --undistort-dir DIR"
        ) from e
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
