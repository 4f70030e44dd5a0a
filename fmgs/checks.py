"""Small validators that name the field and the first bad row."""

from __future__ import annotations

import torch

from fmgs.errors import ValidationError


def first_bad_row(bad: torch.Tensor) -> int | None:
    """Index along dim 0 of the first row where ``bad`` (any shape [N,...]) is true, else None."""
    if bad.ndim > 1:
        bad = bad.flatten(1).any(dim=1) if bad.numel() else bad.new_zeros(bad.shape[0])
    idx = torch.nonzero(bad, as_tuple=False)
    return int(idx[0, 0]) if idx.numel() else None


def check_finite(name: str, t: torch.Tensor) -> None:
    """Raise ValidationError naming ``name`` and the first row holding NaN or Inf."""
    if not t.is_floating_point():
        raise ValidationError(name, f"expected a floating-point tensor, got {t.dtype}")
    # One reduction pass, no temporary: a NaN or Inf anywhere makes the sum non-finite. A finite sum
    # proves the tensor clean; a non-finite one (possibly just overflow) falls through to the exact search.
    if t.numel() == 0 or bool(torch.isfinite(t.sum())):
        return
    row = first_bad_row(~torch.isfinite(t))
    if row is not None:
        raise ValidationError(name, "contains NaN or Inf", row)


def check_shape(name: str, t: torch.Tensor, shape: tuple[int | None, ...]) -> None:
    """Raise ValidationError unless ``t.shape`` matches ``shape`` (None matches any size)."""
    ok = t.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, t.shape, strict=True))
    if not ok:
        want = "[" + ",".join("*" if s is None else str(s) for s in shape) + "]"
        raise ValidationError(name, f"expected shape {want}, got {list(t.shape)}")
