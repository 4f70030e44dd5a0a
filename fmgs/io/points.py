"""Coloured point clouds as PLY (x, y, z float32; red, green, blue uint8): the sparse points a dataset
carries (``ply_file_path``) for the 3DGS stage to start from."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fmgs.errors import ValidationError
from fmgs.io.atomic import atomic_path


def write_point_ply(path: Path, pts: np.ndarray, cols: np.ndarray) -> None:
    """Write points [P,3] with colours [P,3] uint8, atomically."""
    from plyfile import PlyData, PlyElement

    rec = np.empty(
        len(pts),
        dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")],
    )
    for i, k in enumerate("xyz"):
        rec[k] = pts[:, i]
    for i, k in enumerate(("red", "green", "blue")):
        rec[k] = cols[:, i]
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(rec, "vertex")]).write(str(tmp))


def read_point_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(points [P,3] float64, colours [P,3] uint8; grey where the file has none). Points with a NaN or
    Inf coordinate are dropped; a file that is not a point PLY raises ValidationError naming it."""
    from plyfile import PlyData, PlyParseError

    try:
        ply = PlyData.read(str(path))
        v = ply["vertex"]
        pts = np.stack([np.asarray(v[k], dtype=np.float64) for k in ("x", "y", "z")], 1)
    except (PlyParseError, ValueError, EOFError, OSError, KeyError) as e:
        raise ValidationError(str(path), f"not a readable point PLY with vertex x, y, z ({e})") from e
    names = {p.name for p in v.properties}
    if {"red", "green", "blue"} <= names:
        cols = np.stack([np.asarray(v[k]) for k in ("red", "green", "blue")], 1).astype(np.uint8)
    else:
        cols = np.full((len(pts), 3), 128, dtype=np.uint8)
    keep = np.isfinite(pts).all(axis=1)
    return pts[keep], cols[keep]
