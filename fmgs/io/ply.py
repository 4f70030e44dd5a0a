"""Read and write 3DGS scenes in the graphdeco PLY layout.

Vertex properties, all float32, in this order::

    x y z nx ny nz f_dc_0..2 f_rest_0..(3*(K-1)-1) opacity scale_0..2 rot_0..3

``f_rest`` is channel-major (all of red's higher-order coefficients, then green's, then blue's);
``scale_*`` are log standard deviations, ``opacity`` is a logit and ``rot_*`` is a wxyz quaternion.
Files from graphdeco, gsplat and nerfstudio exports use this layout; normals may be absent.
A file we write and read back is bit-identical, and so is the float32 data of any file we read, except
that a Mip-Splatting ``filter_3D`` column is folded into the scales and opacities (as its own
``save_fused_ply`` does). Other extra vertex properties are ignored with one warning per file.

``read_ply`` is the one entry point for 3DGS files: it also reads antimatter15 ``.splat`` files (by
suffix, ``fmgs.io.splat``) and SuperSplat / PlayCanvas compressed PLY files (by their header,
``fmgs.io.compressed_ply``).
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np
import torch

from fmgs.errors import ValidationError
from fmgs.gaussians import GaussianSet, sh_degree_from_bases
from fmgs.io.atomic import atomic_path
from fmgs.io.compressed_ply import decode_compressed_ply, is_compressed
from fmgs.io.formats import GRAPHDECO_PLY, fail, gaussian_set
from fmgs.io.splat import read_splat

log = logging.getLogger(__name__)

_REST = re.compile(r"^f_rest_(\d+)$")
_LAYOUT = {"x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2"}
_LAYOUT |= {"rot_0", "rot_1", "rot_2", "rot_3"}
# Read and dropped without a word: normals (zeros in every trainer) and the 8-bit preview colour some
# exporters add beside f_dc.
_IGNORED = {"nx", "ny", "nz", "red", "green", "blue"}
FILTER_3D = "filter_3D"


def _column(vertex, name: str, path: Path) -> np.ndarray:
    try:
        return np.asarray(vertex[name], dtype=np.float32)
    except (KeyError, ValueError) as e:
        raise fail(path, GRAPHDECO_PLY, f"PLY vertex element lacks property {name!r}") from e


def read_ply(path: str | os.PathLike) -> GaussianSet:
    """Load a 3DGS file as a float32 GaussianSet (validated: finite, non-zero quats).

    Reads graphdeco-layout PLY, SuperSplat compressed PLY (told apart by the header) and, by the
    ``.splat`` suffix, antimatter15 ``.splat``. A file that does not decode raises ValidationError
    naming the file and the format it was read as.
    """
    from plyfile import PlyData, PlyParseError  # lazy: plyfile is a core extra

    path = Path(path)
    if path.suffix.lower() == ".splat":
        return read_splat(path)
    if not path.is_file():
        raise ValidationError(str(path), "no such file")
    try:
        ply = PlyData.read(str(path))
    except (PlyParseError, ValueError, EOFError, OSError) as e:
        raise ValidationError(str(path), f"not a readable PLY file ({e})") from e

    if is_compressed(ply):
        return decode_compressed_ply(ply, path)
    if "vertex" not in ply:
        raise ValidationError(str(path), "PLY has no 'vertex' element")
    v = ply["vertex"]
    names = [p.name for p in v.properties]
    rest = sorted((int(m.group(1)), n) for n in names if (m := _REST.match(n)))
    if [i for i, _ in rest] != list(range(len(rest))) or len(rest) % 3:
        raise fail(
            path, GRAPHDECO_PLY, f"f_rest_* properties must be f_rest_0..f_rest_{{3k-1}}, got {len(rest)}"
        )
    k = len(rest) // 3 + 1
    try:
        sh_degree_from_bases(k)
    except ValidationError as e:
        raise fail(path, GRAPHDECO_PLY, f"{len(rest)} f_rest_* properties: {e.reason}") from e
    unknown = [n for n in names if n not in _LAYOUT | _IGNORED | {FILTER_3D} and not _REST.match(n)]
    if unknown:
        log.warning("%s: ignoring vertex properties %s (not in the graphdeco 3DGS layout)", path, unknown)

    def cols(*ns: str) -> np.ndarray:
        return np.stack([_column(v, n, path) for n in ns], axis=1)

    n = len(v.data)
    sh = np.empty((n, k, 3), dtype=np.float32)
    sh[:, 0, :] = cols("f_dc_0", "f_dc_1", "f_dc_2")
    if k > 1:
        sh[:, 1:, :] = cols(*(name for _, name in rest)).reshape(n, 3, k - 1).transpose(0, 2, 1)
    log_scales = cols("scale_0", "scale_1", "scale_2")
    opacity_logits = _column(v, "opacity", path).copy()
    if FILTER_3D in names:
        filt = _column(v, FILTER_3D, path)
        log_scales, opacity_logits = _fold_filter_3d(log_scales, opacity_logits, filt, path)
        log.info("%s: folded Mip-Splatting's %s into the scales and opacities", path, FILTER_3D)
    return gaussian_set(
        path,
        GRAPHDECO_PLY,
        means=cols("x", "y", "z"),
        quats=cols("rot_0", "rot_1", "rot_2", "rot_3"),
        log_scales=log_scales,
        opacity_logits=opacity_logits,
        sh=sh,
    )


def _fold_filter_3d(
    log_scales: np.ndarray, opacity_logits: np.ndarray, filt: np.ndarray, path: Path
) -> tuple[np.ndarray, np.ndarray]:
    """Mip-Splatting's 3D smoothing filter folded in: log scales [N,3] and logits [N] float32.

    ``filt`` [N] is a standard deviation convolved into each Gaussian: scales' = sqrt(scales^2 + filt^2)
    and, to keep the integral, opacity' = opacity * sqrt(det(S^2) / det(S^2 + filt^2)), as Mip-Splatting
    renders and as its ``save_fused_ply`` stores.
    """
    bad = ~np.isfinite(filt)
    if bad.any():
        raise fail(path, GRAPHDECO_PLY, f"{FILTER_3D} contains NaN or Inf", int(np.argmax(bad)))
    ls = log_scales.astype(np.float64)
    with np.errstate(divide="ignore"):  # log(0) = -inf is exact here: those rows are kept as read
        log_f2 = 2.0 * np.log(np.abs(filt.astype(np.float64)))
    fused = 0.5 * np.logaddexp(2.0 * ls, log_f2[:, None])
    # log opacity' = log sigmoid(o) + sum(log s - log s'), all in logs so tiny scales do not underflow.
    log_op = -np.logaddexp(0.0, -opacity_logits.astype(np.float64)) + (ls - fused).sum(axis=1)
    # Rows whose float32 scales the filter does not change keep their bits (and a saturated opacity
    # its finite logit, where log_op would round to 0).
    keep = (fused.astype(np.float32) == log_scales).all(axis=1)
    logits = log_op - np.log(-np.expm1(np.minimum(log_op, -1e-300)))
    return (
        np.where(keep[:, None], log_scales, fused.astype(np.float32)),
        np.where(keep, opacity_logits, logits.astype(np.float32)),
    )


def ply_property_names(sh_degree: int) -> list[str]:
    """The graphdeco property order for a given SH degree."""
    k = (sh_degree + 1) ** 2
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(3 * (k - 1))]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def write_ply(gaussians: GaussianSet, path: str | os.PathLike) -> None:
    """Write ``gaussians`` in the graphdeco layout (binary little-endian float32), atomically."""
    from plyfile import PlyData, PlyElement

    g = gaussians.to(device="cpu", dtype=torch.float32)
    g.validate()
    n, k = g.num, g.sh.shape[1]
    sh = g.sh.detach().numpy()
    columns = [
        g.means.detach().numpy(),
        np.zeros((n, 3), dtype=np.float32),
        sh[:, 0, :],
        sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1)),
        g.opacity_logits.detach().numpy()[:, None],
        g.log_scales.detach().numpy(),
        g.quats.detach().numpy(),
    ]
    flat = np.concatenate(columns, axis=1)
    names = ply_property_names(g.sh_degree)
    rec = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        rec[name] = flat[:, i]
    with atomic_path(path) as tmp:
        PlyData([PlyElement.describe(rec, "vertex")], byte_order="<").write(str(tmp))
