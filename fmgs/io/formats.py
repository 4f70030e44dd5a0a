"""What the 3DGS file readers share: error naming, quantised-alpha decoding, the final validation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from fmgs.errors import ValidationError
from fmgs.gaussians import GaussianSet

GRAPHDECO_PLY = "graphdeco PLY"
SPLAT = "antimatter15 .splat"
COMPRESSED_PLY = "SuperSplat compressed PLY"


def fail(path: Path, fmt: str, reason: str, index: int | None = None) -> ValidationError:
    """A ValidationError naming the file and the format it was read as (raise the result)."""
    return ValidationError(str(path), f"{reason} (read as {fmt})", index)


def alpha_to_logit(alpha: np.ndarray, levels: int) -> np.ndarray:
    """Opacity logits [N] float32 from alphas [N] in [0,1] stored with ``levels`` steps (255 for uint8).

    0 and 1 have infinite logits; they are moved a quarter step inwards: inside the bin they were read
    from, so a writer that rounds to nearest stores the same byte again.
    """
    quarter = 0.25 / levels
    a = np.clip(alpha.astype(np.float64), quarter, 1.0 - quarter)
    return (np.log(a) - np.log1p(-a)).astype(np.float32)


def gaussian_set(
    path: Path,
    fmt: str,
    means: np.ndarray,
    quats: np.ndarray,
    log_scales: np.ndarray,
    opacity_logits: np.ndarray,
    sh: np.ndarray,
) -> GaussianSet:
    """Validate decoded float32 arrays ([N,3], [N,4], [N,3], [N], [N,K,3]) as a GaussianSet.

    A broken contract is re-raised naming the file, the field and the format.
    """
    arrays = (means, quats, log_scales, opacity_logits, sh)
    try:
        return GaussianSet(*(torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)) for a in arrays))
    except ValidationError as e:
        raise ValidationError(f"{path}: {e.field}", f"{e.reason} (read as {fmt})", e.index) from e
