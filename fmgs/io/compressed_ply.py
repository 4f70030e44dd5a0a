"""Decode SuperSplat / PlayCanvas compressed PLY files (``*.compressed.ply``) into a GaussianSet.

The layout, as PlayCanvas's splat-transform writes and reads it:

* element ``chunk``, one row per 256 Gaussians (in file order), float32: ``min_x min_y min_z max_x max_y
  max_z`` (centres), ``min_scale_x .. max_scale_z`` (log scales, clamped to [-20, 20]) and, in newer files,
  ``min_r min_g min_b max_r max_g max_b`` (colour 0.5 + SH_C0 * f_dc; without them colour spans [0,1]);
* element ``vertex``, uint32 ``packed_position`` and ``packed_scale`` (11/10/11 bits, x in the top bits,
  each a fraction of its chunk's [min, max]), ``packed_rotation`` (2 bits: which of rot_0..rot_3 has the
  largest magnitude, made positive; then the other three in order, 10 bits each, mapping
  [-1/sqrt(2), 1/sqrt(2)] to [0, 1023]) and ``packed_color`` (8 bits each: r, g, b as fractions of the
  chunk's range, then alpha = sigmoid(opacity));
* optional element ``sh``, uint8 ``f_rest_0..`` (9, 24 or 45: degree 1..3, graphdeco's channel-major
  order), byte s stands for (s + 0.5) / 256 * 8 - 4 (0 and 255 for -4 and 4 exactly).

Every value is quantised: a decoded value is within half a step of the encoded one (a step is the
chunk's range over 2^bits - 1; 1/32 for SH), except the largest quaternion component, which is
rebuilt from the unit norm and carries the others' error.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from fmgs.gaussians import SH_C0, GaussianSet
from fmgs.io.formats import COMPRESSED_PLY, alpha_to_logit, fail, gaussian_set

CHUNK_SIZE = 256
_POSITION = ("min_x", "min_y", "min_z", "max_x", "max_y", "max_z")
_SCALE = ("min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z")
_COLOR = ("min_r", "min_g", "min_b", "max_r", "max_g", "max_b")
_PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")
# For each index of the largest component: where the three stored components go.
_OTHERS = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])


def is_compressed(ply) -> bool:
    """Whether a parsed ``plyfile.PlyData`` claims the compressed layout (a chunk element or packed data)."""
    names = [e.name for e in ply.elements]
    vertex_props = (ply["vertex"].data.dtype.names or ()) if "vertex" in names else ()
    return "chunk" in names or any(p in vertex_props for p in _PACKED)


def _unorm(v: np.ndarray, shift: int, bits: int) -> np.ndarray:
    """The ``bits``-wide field of ``v`` [N] starting ``shift`` bits up, as a fraction in [0,1] float64."""
    top = (1 << bits) - 1
    return ((v >> np.uint32(shift)) & np.uint32(top)).astype(np.float64) / top


def _lerp(lo: np.ndarray, hi: np.ndarray, t: np.ndarray) -> np.ndarray:
    return lo * (1.0 - t) + hi * t


def decode_compressed_ply(ply, path: Path) -> GaussianSet:
    """Decode a parsed ``plyfile.PlyData`` in the compressed layout; ValidationError naming the file."""
    names = [e.name for e in ply.elements]
    for need in ("chunk", "vertex"):
        if need not in names:
            raise fail(path, COMPRESSED_PLY, f"no {need!r} element")
    chunk, vertex = ply["chunk"].data, ply["vertex"].data
    cprops, vprops = chunk.dtype.names or (), vertex.dtype.names or ()
    for prop in (*_POSITION, *_SCALE):
        if prop not in cprops:
            raise fail(path, COMPRESSED_PLY, f"chunk element lacks property {prop!r}")
    for prop in _PACKED:
        if prop not in vprops:
            raise fail(path, COMPRESSED_PLY, f"vertex element lacks property {prop!r}")
        if (vertex.dtype[prop].kind, vertex.dtype[prop].itemsize) != ("u", 4):
            raise fail(path, COMPRESSED_PLY, f"{prop} must be uint32, got {vertex.dtype[prop]}")
    n = len(vertex)
    if n == 0:
        raise fail(path, COMPRESSED_PLY, "no Gaussians")
    if len(chunk) != math.ceil(n / CHUNK_SIZE):
        raise fail(
            path, COMPRESSED_PLY, f"{len(chunk)} chunks for {n} Gaussians, expected ceil({n}/{CHUNK_SIZE})"
        )
    ci = np.arange(n) // CHUNK_SIZE

    def bounds(props: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        """[N,3] lower and upper bounds per Gaussian, from its chunk."""
        c = np.stack([chunk[p].astype(np.float64) for p in props], axis=1)[ci]
        return c[:, :3], c[:, 3:]

    def fractions(v: np.ndarray, bits: tuple[int, int, int]) -> np.ndarray:
        """[N,3] the three fields of a packed word, highest bits first."""
        shifts = (bits[1] + bits[2], bits[2], 0)
        return np.stack([_unorm(v, s, b) for s, b in zip(shifts, bits, strict=True)], axis=1)

    packed = {p: vertex[p].astype(np.uint32) for p in _PACKED}
    means = _lerp(*bounds(_POSITION), fractions(packed["packed_position"], (11, 10, 11)))
    log_scales = _lerp(*bounds(_SCALE), fractions(packed["packed_scale"], (11, 10, 11)))

    rgba = fractions(packed["packed_color"] >> np.uint32(8), (8, 8, 8))
    alpha = _unorm(packed["packed_color"], 0, 8)
    if all(p in cprops for p in _COLOR):
        rgba = _lerp(*bounds(_COLOR), rgba)
    f_dc = (rgba - 0.5) / SH_C0

    rot = packed["packed_rotation"]
    small = (fractions(rot, (10, 10, 10)) - 0.5) * math.sqrt(2.0)
    largest = (rot >> np.uint32(30)).astype(np.intp)
    quats = np.empty((n, 4))
    rows = np.arange(n)
    quats[rows[:, None], _OTHERS[largest]] = small
    quats[rows, largest] = np.sqrt(np.maximum(0.0, 1.0 - (small * small).sum(axis=1)))

    sh = f_dc[:, None, :]
    if "sh" in names:
        sh = np.concatenate([sh, _sh_rest(ply["sh"].data, n, path)], axis=1)
    return gaussian_set(
        path,
        COMPRESSED_PLY,
        means=means,
        quats=quats,
        log_scales=log_scales,
        opacity_logits=alpha_to_logit(alpha, 255),
        sh=sh,
    )


def _sh_rest(data: np.ndarray, n: int, path: Path) -> np.ndarray:
    """[N,K-1,3] higher-order SH from the uint8 ``sh`` element (f_rest_0.., channel-major)."""
    m = len(data.dtype.names or ())
    if m not in (9, 24, 45):
        raise fail(path, COMPRESSED_PLY, f"sh element has {m} properties, expected 9, 24 or 45")
    if len(data) != n:
        raise fail(path, COMPRESSED_PLY, f"sh element has {len(data)} rows for {n} Gaussians")
    cols = []
    for i in range(m):
        name = f"f_rest_{i}"
        if name not in data.dtype.names or data.dtype[name] != np.uint8:
            raise fail(path, COMPRESSED_PLY, f"sh element needs uint8 {name}")
        cols.append(data[name])
    s = np.stack(cols, axis=1).astype(np.float64)
    # Bytes are bins of width 1/256 over [-4, 4]; the end bytes stand for the clamped ends exactly.
    frac = np.where(s == 0, 0.0, np.where(s == 255, 1.0, (s + 0.5) / 256.0))
    return ((frac - 0.5) * 8.0).reshape(n, 3, m // 3).transpose(0, 2, 1)
