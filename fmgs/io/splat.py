"""Read antimatter15's ``.splat`` files (the web viewer's format) into a GaussianSet.

A ``.splat`` file has no header: 32 bytes per Gaussian, little-endian::

    x y z            3 x float32   centre
    sx sy sz         3 x float32   linear standard deviations (not log)
    r g b a          4 x uint8     (0.5 + SH_C0 * f_dc) * 255 and sigmoid(opacity) * 255, clipped
    qw qx qy qz      4 x uint8     unit quaternion * 128 + 128, clipped

Only the DC colour survives (degree-0 SH); colours outside [0,1] were clipped by the writer. Decoded
values are within one storage step of what was written: 1/255 for colour and alpha, 1/128 for the
quaternion components (writers differ in rounding or truncating).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from fmgs.gaussians import SH_C0, GaussianSet
from fmgs.io.formats import SPLAT, alpha_to_logit, fail, gaussian_set

# 12 + 12 + 4 + 4 = 32 bytes, no padding.
RECORD = np.dtype([("means", "<f4", 3), ("scales", "<f4", 3), ("rgba", "u1", 4), ("quat", "u1", 4)])


def read_splat(path: str | os.PathLike) -> GaussianSet:
    """Load a ``.splat`` file as a float32 degree-0 GaussianSet (validated: finite, non-zero quats)."""
    path = Path(path)
    if not path.is_file():
        raise fail(path, SPLAT, "no such file")
    size = path.stat().st_size
    if size == 0 or size % RECORD.itemsize:
        raise fail(path, SPLAT, f"size {size} bytes is not a positive multiple of 32 (truncated?)")
    rec = np.fromfile(path, dtype=RECORD)
    scales = rec["scales"].astype(np.float64)
    bad = ~(np.isfinite(scales) & (scales > 0)).all(axis=1)
    if bad.any():
        raise fail(path, SPLAT, "scales must be finite and positive", int(np.argmax(bad)))
    rgba = rec["rgba"].astype(np.float64) / 255.0
    quats = (rec["quat"].astype(np.float32) - 128.0) / 128.0
    return gaussian_set(
        path,
        SPLAT,
        means=rec["means"],
        quats=quats,
        log_scales=np.log(scales),
        opacity_logits=alpha_to_logit(rgba[:, 3], 255),
        sh=((rgba[:, :3] - 0.5) / SH_C0)[:, None, :],
    )
