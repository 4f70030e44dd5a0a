"""A relevancy image is scored in bands of rows, so that a server sees its deadline between them: the bands
do not depend on whether a deadline is checked, so neither does the image; banded or scored at once, it is
the float64 reference's up to float32 rounding, and argmax and ties follow row-major order."""

from __future__ import annotations

import pytest
import torch

import fmgs.query.pose as pose
from fmgs.query.pose import score_image
from fmgs.query.relevancy import TEMPERATURE, relevancy_reference
from tests.helpers.tolerances import assert_close


def _clip_like(h: int, w: int, c: int, seed: int) -> torch.Tensor:
    """Rendered channels [h,w,1+c] in CLIP's range: query and canonical dots between -0.1 and 0.35."""
    g = torch.Generator().manual_seed(seed)
    return torch.rand(h, w, 1 + c, generator=g) * 0.45 - 0.1


@pytest.mark.parametrize(
    "h,w,band", [(37, 53, 200), (40, 48, 48 * 5), (7, 1000, 10), (1, 1, 1), (64, 64, 1 << 20)]
)
def test_the_image_does_not_depend_on_the_deadline_check(monkeypatch, h, w, band):
    img = _clip_like(h, w, 4, h * w)
    monkeypatch.setattr(pose, "SCORE_BAND_PIXELS", band)
    calls = []
    checked, arg_checked = score_image(img, lambda: calls.append(1))
    unchecked, arg_unchecked = score_image(img)
    assert torch.equal(checked, unchecked) and arg_checked == arg_unchecked
    rows = max(1, band // w)
    assert len(calls) == (-(-h // rows) if rows < h else 0)  # one check per band; none when one band
    ref = relevancy_reference(img[..., 0], img[..., 1:], TEMPERATURE)
    assert_close(checked, ref, torch.float32, "banded relevancy")
    x, y, v = arg_checked
    first = int(torch.nonzero(checked.flatten() == checked.max())[0])
    assert (y * w + x, v) == (first, float(checked.max()))


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
