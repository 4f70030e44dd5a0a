"""benchmarks/text.py's batch measurement runs against the engine's current query plan (it calls the bound
passes of fmgs.query.plan directly), on a compact-path scene large enough for the sample estimate."""

from __future__ import annotations

import math

import pytest
import torch

from benchmarks import text
from benchmarks.query_sets import query_sets
from fmgs.query.engine import EngineConfig, SceneEngine
from fmgs.query.index import IndexConfig

pytestmark = pytest.mark.slow  # a 70K-row compact package and timed rounds


def test_batch_measurement_runs_on_the_compact_path(tmp_path):
    n = 70_000  # at least TIER2_FIRST_MIN_SAMPLE * TIER2_FIRST_STEP rows: hints are estimated
    pkg, copies, _ = text.package(tmp_path, n)
    eng = SceneEngine.open(pkg, EngineConfig(index=IndexConfig(exact_below=0)))
    assert not eng.index.exact and eng.index.compact.estimates_first_pass
    emb, _ = text.stored(pkg)
    sets = query_sets(emb, copies, 8)
    res: dict = {}
    text.batch(eng, sets, res)
    for name in ("typical", "clip"):
        for key in ("batch8", "one", "bound8", "bound1"):
            ms = res[f"{key}_{name}_ms"]
            assert math.isfinite(ms) and ms > 0
        assert res[f"batch8_{name}_ratio"] > 0
        for key in ("batch8", "one8"):
            major, minor, read = res[f"{key}_{name}_faults"]
            assert major >= 0 and minor >= 0 and read >= 0
    # The batch's answers are the texts' own (what the timing measured is the served path).
    qs = sets["typical"][:8]
    many = eng.text_query_many(qs, 100)
    for q, a in zip(qs, many, strict=True):
        assert torch.equal(a.index, eng.text_query(q, 100).index)
