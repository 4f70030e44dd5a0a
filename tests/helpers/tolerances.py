"""One tolerance table and one assert helper for every numerical comparison in the suite."""

from __future__ import annotations

import numpy as np
import torch

# Relative error (max |a - b| / max |b|) allowed against the float64 brute force, by the dtype the
# features were blended in. Geometry is float64 in every backend, so only blending rounding remains.
# Half dtypes: images rounded once to them (unit roundoff 4.9e-4 for float16, 3.9e-3 for bfloat16).
RTOL = {torch.float32: 1e-5, torch.float64: 1e-10, torch.float16: 1e-3, torch.bfloat16: 1e-2}


def as_np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().to(torch.float64).numpy()
    return np.asarray(x, dtype=np.float64)


def rel_err(actual, expected) -> float:
    """max |actual - expected| / max |expected| (absolute error when expected is all zero)."""
    a, e = as_np(actual), as_np(expected)
    assert a.shape == e.shape, f"shape {a.shape} != {e.shape}"
    assert np.isfinite(a).all(), "non-finite values in the result"
    scale = np.abs(e).max() if e.size else 0.0
    diff = np.abs(a - e).max() if e.size else 0.0
    return float(diff / scale) if scale > 0 else float(diff)


def assert_close(actual, expected, dtype: torch.dtype, what: str = "") -> None:
    err = rel_err(actual, expected)
    tol = RTOL[dtype]
    assert err <= tol, f"{what}: relative error {err:.3e} > {tol:.0e} ({dtype})"
