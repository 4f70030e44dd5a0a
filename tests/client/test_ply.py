"""The client's PLY writer and reader (``fmgs_client.ply``)."""

from __future__ import annotations

import numpy as np
import pytest

from fmgs_client.ply import read_ply, write_ply


def test_ply_round_trip(tmp_path):
    rng = np.random.default_rng(7)
    n = 50
    pts = rng.normal(size=(n, 3)).astype(np.float32)
    col = rng.integers(0, 256, (n, 3), dtype=np.uint8)
    rel = rng.random(n).astype(np.float32)
    idx = rng.integers(0, 10**6, n).astype(np.int64)
    path = write_ply(
        tmp_path / "p.ply", pts, col, {"relevancy": rel, "gaussian": idx, "d": rel.astype(">f8")}
    )
    back = read_ply(path)
    np.testing.assert_array_equal(back.points, pts)
    np.testing.assert_array_equal(back.colors, col)
    assert list(back.scalars) == ["relevancy", "gaussian", "d"]
    np.testing.assert_array_equal(back.scalars["relevancy"], rel)
    np.testing.assert_array_equal(back.scalars["gaussian"], idx)
    assert back.scalars["gaussian"].dtype == np.int32 and back.scalars["d"].dtype == np.float64
    empty = read_ply(write_ply(tmp_path / "e.ply", np.zeros((0, 3))))
    assert empty.points.shape == (0, 3) and empty.colors is None
    with pytest.raises(ValueError, match="must be"):
        write_ply(tmp_path / "bad.ply", pts, col, {"relevancy": rel[:3]})
    with pytest.raises(ValueError, match="int32"):
        write_ply(tmp_path / "bad.ply", pts, None, {"g": np.full(n, 2**40)})
