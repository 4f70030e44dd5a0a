"""Small validators that name the field and the first bad row."""

from __future__ import annotations

import torch

from fmgs.errors import ValidationError

_BLOCK = 1 << 22  # elements per finiteness block


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
    if t.numel() == 0:
        return
    if t.ndim == 0:
        t = t.reshape(1)
    # A reduction per block of rows: a NaN or Inf anywhere makes the block's sum non-finite. A finite
    # sum proves the block clean; a non-finite one (possibly just overflow) falls through to the exact
    # search. Blocks, because a reduction may make a temporary copy (a float16 sum on a CPU upcasts the
    # whole tensor: 20 GB for a 10M x 512 scene's embeddings).
    step = max(1, _BLOCK // max(1, t[0].numel()))
    for s in range(0, t.shape[0], step):
        b = t[s : s + step]
        if bool(torch.isfinite(b.sum())):
            continue
        row = first_bad_row(~torch.isfinite(b))
        if row is not None:
            raise ValidationError(name, "contains NaN or Inf", s + row)


def check_shape(name: str, t: torch.Tensor, shape: tuple[int | None, ...]) -> None:
    """Raise ValidationError unless ``t.shape`` matches ``shape`` (None matches any size)."""
    ok = t.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, t.shape, strict=True))
    if not ok:
        want = "[" + ",".join("*" if s is None else str(s) for s in shape) + "]"
        raise ValidationError(name, f"expected shape {want}, got {list(t.shape)}")


def damaged_embedding(row: int) -> ValidationError:
    """The error for a stored embedding ``row`` that is not finite (a damaged package)."""
    return ValidationError("embeddings", f"row {row} is not finite: the package is damaged")


def check_rows_finite(values: torch.Tensor, rows) -> None:
    """Raise ``damaged_embedding`` for the first of ``rows`` [k] whose scores ``values`` [k,n] are not
    finite."""
    if not bool(torch.isfinite(values).all()):
        raise damaged_embedding(int(rows[int((~torch.isfinite(values)).any(1).nonzero()[0, 0])]))
