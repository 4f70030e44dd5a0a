"""The work-precision report's helpers (benchmarks/workprec/measure.py): error measures, the exact-point
check, floors and growth fits."""

from __future__ import annotations

import math

import pytest
import torch

from benchmarks.workprec.measure import (
    Cost,
    Rates,
    exact_failures,
    fit_growth,
    floor_ms,
    image_error,
    interleaved,
    overlap_error,
    render_cost,
    sorted_relevancy_error,
    text_query_cost,
)


def test_overlap_error():
    assert overlap_error([1, 2, 3, 4], [4, 3, 2, 1], 4) == 0
    assert overlap_error([1, 2, 3, 4], [1, 2, 5, 6], 4) == 0.5
    assert overlap_error([1, 2, 3, 9], [1, 2, 3, 4, 9], 3) == 0  # only the first k of each list count


def test_sorted_relevancy_error():
    a = torch.tensor([0.9, 0.8, 0.7])
    assert sorted_relevancy_error(a, a.clone()) == 0
    assert sorted_relevancy_error(a, torch.tensor([0.9, 0.75, 0.7])) == pytest.approx(0.05)
    assert sorted_relevancy_error(a, a[:2]) == 1.0


def test_image_error():
    ref = torch.zeros(4, 5)
    ref[1, 2] = 1.0
    assert image_error(ref, ref.clone()) == (0.0, 0.0, True, 0.0)
    moved = torch.zeros(4, 5)
    moved[3, 3] = 0.5
    err = image_error(moved, ref)
    assert err.max_abs == 1.0 and err.mean_abs == pytest.approx(1.5 / 20) and not err.argmax_same
    assert err.argmax_px == pytest.approx(math.hypot(2, 1))


def _point(exact: bool, errors: dict) -> dict:
    return {"curve": "c", "label": "l", "exact": exact, "errors": errors}


def test_exact_failures_flags_only_exact_points_with_nonzero_error():
    ok = {"text": {"points": [_point(True, {"a": 0.0, "b": 0.0}), _point(False, {"a": 0.3})]}}
    assert exact_failures(ok) == []
    bad = {"pose": {"points": [_point(True, {"a": 0.0, "b": 1e-12})]}, "floor": {"rows": []}}
    [msg] = exact_failures(bad)
    assert msg.startswith("pose/c/l") and "1e-12" in msg


def test_exact_point_of_a_tiny_text_query_is_zero():
    """The index's exact path against its reference twin, as the text section compares them."""
    from fmgs.query.index import EmbeddingIndex, IndexConfig
    from fmgs.query.reference import rank_reference

    g = torch.Generator().manual_seed(0)
    emb = torch.nn.functional.normalize(torch.randn(500, 32, generator=g), dim=1)
    canon = emb[:, :4] * 0.5
    idx = EmbeddingIndex.build(emb, canon, IndexConfig(rank=0))
    for q in torch.nn.functional.normalize(torch.randn(3, 32, generator=g), dim=1):
        a, r = idx.rank(q, 20), rank_reference(emb, canon, q, 20)
        assert overlap_error(a.rows.tolist(), r.rows.tolist(), 20) == 0
        assert sorted_relevancy_error(a.relevancy, r.relevancy) == 0


def test_floor_is_the_slower_of_memory_and_arithmetic():
    rates = Rates(bandwidth_gbs=10.0, gflops=100.0)
    assert floor_ms(Cost(1e9, 1.0), rates) == pytest.approx(100.0)  # 1 GB at 10 GB/s
    assert floor_ms(Cost(1.0, 1e10), rates) == pytest.approx(100.0)  # 10 GFLOP at 100 GFLOP/s
    c = text_query_cost(1_000_000, 64)
    assert c.bytes == 1_000_000 * 76 and c.flops == 2 * 64 * 1_000_000
    assert text_query_cost(10, 64, rerank_rows=100).bytes == 10 * 76 + 100 * 512 * 2
    r = render_cost(pairs=1000, gaussians=10, pixels=100, channels=5)
    assert r.flops > 1000 * 10 and r.bytes == 10 * 19 * 4 + 100 * 7 * 4


def test_fit_growth_recognises_linear_and_fixed_cost():
    n = [1e4, 1e5, 1e6, 1e7]
    lin = fit_growth(n, [2 + x * 1e-5 for x in n])
    assert lin.model == "linear" and math.isclose(lin.exponent, 1.0, abs_tol=0.1)
    assert lin.fixed_ms == pytest.approx(2, rel=1e-6) and lin.per_unit_ns == pytest.approx(10, rel=1e-6)
    assert (lin.linear_lo, lin.linear_hi) == (1e6, 1e7)  # below 1e6 the fixed 2 ms dominates
    assert lin.best_unit_ns == pytest.approx(10.2) and lin.top_unit_ns == lin.best_unit_ns
    jump = fit_growth(n, [1.0, 10.0, 100.0, 3000.0])  # linear, then 3x per unit at the top
    assert (jump.linear_lo, jump.linear_hi) == (1e4, 1e6) and jump.top_unit_ns == pytest.approx(300)
    flat = fit_growth(n, [5.0, 5.0, 5.1, 5.0])
    assert flat.model == "sub-linear"
    nlogn = fit_growth(n, [x * math.log2(x) * 1e-6 for x in n])
    assert nlogn.rel_rms_nlogn < 1e-9 < nlogn.rel_rms_linear


def test_interleaved_runs_every_setting_on_every_input():
    calls = []
    fns = {k: (lambda i, k=k: calls.append((k, i)) or (k, i)) for k in "abc"}
    times, outs = interleaved(fns, 2, reps=2)
    assert all(len(t) == 4 for t in times.values())
    assert outs["b"] == [("b", 0), ("b", 1)]
    assert len(calls) == 3 + 3 * 2 * 2  # warm-up + reps x inputs x settings
    assert [c[0] for c in calls[3:6]] != [c[0] for c in calls[6:9]]  # order rotates
