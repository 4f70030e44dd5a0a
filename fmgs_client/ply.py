"""Binary little-endian PLY point clouds: points [N,3], colours uint8 [N,3], optional scalar properties.

Written without plyfile so the thin client needs nothing beyond numpy; the files open in Open3D,
MeshLab and CloudCompare (``x y z red green blue`` plus extra ``float``/``int`` vertex properties).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fmgs_client.types import require_finite

# numpy dtype <-> PLY scalar type names (little-endian on disk).
_PLY_TYPES = {
    np.dtype("float32"): "float",
    np.dtype("float64"): "double",
    np.dtype("int8"): "char",
    np.dtype("uint8"): "uchar",
    np.dtype("int16"): "short",
    np.dtype("uint16"): "ushort",
    np.dtype("int32"): "int",
    np.dtype("uint32"): "uint",
}
_NAMES = {
    **{v: k for k, v in _PLY_TYPES.items()},
    "float32": np.dtype("float32"),
    "float64": np.dtype("float64"),
    "int8": np.dtype("int8"),
    "uint8": np.dtype("uint8"),
    "int16": np.dtype("int16"),
    "uint16": np.dtype("uint16"),
    "int32": np.dtype("int32"),
    "uint32": np.dtype("uint32"),
}


@dataclass(frozen=True, eq=False)
class PlyPoints:
    """A point cloud read back from PLY."""

    points: np.ndarray
    """[N,3] float32 positions."""
    colors: np.ndarray | None
    """[N,3] uint8 colours, or None when the file has none."""
    scalars: dict[str, np.ndarray] = field(default_factory=dict)
    """Further per-point properties by name, [N] each, in file order."""


def _scalar_dtype(name: str, a: np.ndarray) -> np.dtype:
    dt = a.dtype.newbyteorder("=") if a.dtype.byteorder not in ("=", "|") else a.dtype
    if dt == np.int64 or dt == np.uint64:
        # PLY has no 64-bit integers; Gaussian indices fit int32 in any realistic scene.
        if a.size and (a.min() < np.iinfo(np.int32).min or a.max() > np.iinfo(np.int32).max):
            raise ValueError(f"write_ply: property {name!r} does not fit int32")
        return np.dtype("int32")
    if dt == np.bool_:
        return np.dtype("uint8")
    if dt not in _PLY_TYPES:
        raise ValueError(f"write_ply: property {name!r} has unsupported dtype {a.dtype}")
    return dt


def write_ply(
    path: str | Path,
    points: np.ndarray,
    colors: np.ndarray | None = None,
    scalars: dict[str, np.ndarray] | None = None,
) -> Path:
    """Write points [N,3] (as float32), optional colours uint8 [N,3] and scalar properties [N] each;
    ValueError (nothing written) for NaN or infinity among the points or a float property."""
    pts = np.asarray(points, np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"write_ply: points must be [N,3], got {pts.shape}")
    require_finite(pts, "write_ply: points")
    n = len(pts)
    fields: list[tuple[str, np.dtype, np.ndarray]] = [
        (ax, np.dtype("float32"), pts[:, i]) for i, ax in enumerate("xyz")
    ]
    if colors is not None:
        col = np.asarray(colors)
        if col.shape != (n, 3) or col.dtype != np.uint8:
            raise ValueError(f"write_ply: colors must be uint8 [{n},3], got {col.dtype} {col.shape}")
        fields += [(c, np.dtype("uint8"), col[:, i]) for i, c in enumerate(("red", "green", "blue"))]
    for name, values in (scalars or {}).items():
        a = np.asarray(values)
        if a.shape != (n,):
            raise ValueError(f"write_ply: property {name!r} must be [{n}], got {a.shape}")
        if not name.isidentifier() or name in ("x", "y", "z", "red", "green", "blue"):
            raise ValueError(f"write_ply: bad property name {name!r}")
        require_finite(a, f"write_ply: property {name!r}")
        fields.append((name, _scalar_dtype(name, a), a))
    rec = np.empty(n, dtype=[(name, dt.newbyteorder("<")) for name, dt, _ in fields])
    for name, dt, a in fields:
        rec[name] = a.astype(dt)
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment written by fmgs_client",
        f"element vertex {n}",
    ]
    header += [f"property {_PLY_TYPES[dt]} {name}" for name, dt, _ in fields]
    header.append("end_header")
    path = Path(path)
    with path.open("wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(rec.tobytes())
    return path


def read_ply(path: str | Path) -> PlyPoints:
    """Read a binary little-endian PLY whose only element is ``vertex`` with scalar properties."""
    data = Path(path).read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError(f"{path}: not a PLY file")
    lines = data[:end].decode("ascii").splitlines()
    body = data[end + len(b"end_header\n") :]
    n, props = None, []
    for line in lines[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format" and tok[1] != "binary_little_endian":
            raise ValueError(f"{path}: only binary_little_endian PLY is supported, got {tok[1]}")
        if tok[0] == "element":
            if n is not None or tok[1] != "vertex":
                raise ValueError(f"{path}: only a single 'vertex' element is supported")
            n = int(tok[2])
        if tok[0] == "property":
            if tok[1] == "list" or tok[1] not in _NAMES:
                raise ValueError(f"{path}: unsupported property {' '.join(tok[1:])}")
            props.append((tok[2], _NAMES[tok[1]].newbyteorder("<")))
    if n is None:
        raise ValueError(f"{path}: no vertex element")
    dt = np.dtype(props)
    if len(body) < n * dt.itemsize:
        raise ValueError(f"{path}: truncated ({len(body)} bytes for {n} vertices of {dt.itemsize})")
    rec = np.frombuffer(body[: n * dt.itemsize], dt)
    names = [p for p, _ in props]
    for ax in "xyz":
        if ax not in names:
            raise ValueError(f"{path}: missing property {ax}")
    pts = np.stack([rec[ax] for ax in "xyz"], 1).astype(np.float32)
    colors = None
    if all(c in names for c in ("red", "green", "blue")):
        colors = np.stack([rec[c] for c in ("red", "green", "blue")], 1).astype(np.uint8)
    rest = [p for p in names if p not in ("x", "y", "z", "red", "green", "blue")]
    scalars = {p: rec[p].astype(rec[p].dtype.newbyteorder("=")) for p in rest}
    return PlyPoints(pts, colors, scalars)
