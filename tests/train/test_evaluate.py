"""Held-out evaluation's per-view verdicts: the worst view, the views under the threshold, their marks in
the table and the warning that names them (fmgs.train.evaluate)."""

from __future__ import annotations

from fmgs.train.evaluate import LOW_VIEW_PSNR_DB, EvalResult


def _result(psnrs: list[float]) -> EvalResult:
    views = [{"name": f"{i:04d}.png", "psnr": p, "ssim": 0.5 + p / 100} for i, p in enumerate(psnrs)]
    return EvalResult(sum(psnrs) / len(psnrs), sum(v["ssim"] for v in views) / len(views), views)


def test_a_good_mean_does_not_hide_a_failed_view():
    r = _result([28.0, 11.8, 27.5, 14.6, 29.0])  # mean 22.2 dB: above the threshold
    assert r.psnr > LOW_VIEW_PSNR_DB
    assert [v["name"] for v in r.below()] == ["0001.png", "0003.png"]  # worst first
    assert r.worst["name"] == "0001.png" and r.worst["psnr"] == 11.8
    warning = r.warning()
    assert warning is not None and "2 of 5 held-out views" in warning
    assert "0001.png (11.8 dB)" in warning and "0003.png (14.6 dB)" in warning
    table = r.table()
    assert table.count("**below 20 dB**") == 2 and "| **worst** (0001.png) | **11.80**" in table
    s = r.summary()
    assert s["below"] == ["0001.png", "0003.png"] and s["worst"] == r.worst and len(s["per_view"]) == 5


def test_no_warning_when_every_view_holds():
    r = _result([24.0, 21.0, 30.0])
    assert r.below() == [] and r.warning() is None and "below" not in r.table().replace("| view", "")
    assert r.warning(threshold_db=22.0) is not None  # the threshold is the caller's
