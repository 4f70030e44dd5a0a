"""A relevancy image scored in bands of rows (so a server sees its deadline between them) is the image
scored at once: every pixel is scored alone, so only the vectorised sigmoid's rounding may differ (torch
takes a scalar path for a band's last elements), by at most one float32 step; argmax and ties agree."""

from __future__ import annotations

import pytest
import torch

import fmgs.query.pose as pose
from fmgs.query.pose import score_image

ULP = 2.0**-24
"""One float32 step just below 1 (relevancies lie in (0, 1))."""


def _clip_like(h: int, w: int, c: int, seed: int) -> torch.Tensor:
    """Rendered channels [h,w,1+c] in CLIP's range: query and canonical dots between -0.1 and 0.35."""
    g = torch.Generator().manual_seed(seed)
    return torch.rand(h, w, 1 + c, generator=g) * 0.45 - 0.1


@pytest.mark.parametrize("h,w,band", [(37, 53, 200), (40, 48, 48 * 5), (7, 1000, 10), (1, 1, 1)])
def test_bands_give_the_image_scored_at_once(monkeypatch, h, w, band):
    img = _clip_like(h, w, 4, h * w)
    whole, arg_whole = score_image(img)
    monkeypatch.setattr(pose, "SCORE_BAND_PIXELS", band)
    calls = []
    banded, arg_banded = score_image(img, lambda: calls.append(1))
    rows = max(1, band // w)
    assert float((banded - whole).abs().max()) <= ULP and arg_banded == arg_whole
    assert len(calls) == (-(-h // rows) if rows < h else 0)  # one check per band; none when one band


def test_a_tie_across_bands_keeps_the_first_pixel_in_row_major_order(monkeypatch):
    img = _clip_like(30, 20, 4, 1)
    img[..., 0] = -0.1  # every query dot low ...
    img[3, 17, 0] = img[25, 2, 0] = 0.35  # ... but two equal maxima, in different bands
    img[25, 2, 1:] = img[3, 17, 1:]
    monkeypatch.setattr(pose, "SCORE_BAND_PIXELS", 100)
    rel, (x, y, v) = score_image(img, lambda: None)
    assert (x, y) == (17, 3) and v == float(rel.max())


def test_a_stop_raised_between_bands_ends_the_scoring(monkeypatch):
    monkeypatch.setattr(pose, "SCORE_BAND_PIXELS", 100)
    calls = []

    def stop() -> None:
        calls.append(1)
        if len(calls) == 2:
            raise TimeoutError("deadline")

    with pytest.raises(TimeoutError):
        score_image(_clip_like(50, 20, 4, 2), stop)
    assert len(calls) == 2
