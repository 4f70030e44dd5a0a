"""fmgs.checks: finiteness checked a block of rows at a time, naming the first bad row."""

from __future__ import annotations

import pytest
import torch

import fmgs.checks as checks
from fmgs.errors import ValidationError


@pytest.mark.parametrize("dtype", [torch.float16, torch.float32, torch.float64])
def test_the_first_bad_row_is_named_across_blocks(monkeypatch, dtype):
    monkeypatch.setattr(checks, "_BLOCK", 30)  # 10 rows of 3 per block
    t = torch.ones(95, 3, dtype=dtype)
    checks.check_finite("x", t)
    t[93, 2] = float("inf")
    t[47, 0] = float("nan")
    with pytest.raises(ValidationError, match="at index 47"):
        checks.check_finite("x", t)


def test_a_finite_overflowing_block_is_searched_and_passes(monkeypatch):
    monkeypatch.setattr(checks, "_BLOCK", 8)
    t = torch.full((20, 4), 60000.0, dtype=torch.float16)  # each block's sum overflows float16
    checks.check_finite("x", t)


def test_scalars_and_empty_tensors():
    checks.check_finite("x", torch.tensor(1.0))
    checks.check_finite("x", torch.zeros(0, 5))
    with pytest.raises(ValidationError, match="x at index 0"):
        checks.check_finite("x", torch.tensor(float("nan")))
    with pytest.raises(ValidationError, match="floating-point"):
        checks.check_finite("x", torch.zeros(3, dtype=torch.int64))
