"""Certified exact text answers: every query set, both index paths, against the float64 brute force."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import fmgs.query.certify as certify_mod
import fmgs.query.plan as plan_mod
import fmgs.query.tuning as tuning
from benchmarks.query_sets import QUERY_SETS, query_sets, scene_embeddings
from fmgs.errors import ValidationError
from fmgs.query.certify import (
    Pending,
    Refined,
    _drop_sorted,
    _keep_sorted,
    certified_top_k,
    certify_finish,
    certify_narrow,
    certify_start,
    rows_at_least,
    threshold_margin,
    top_rows,
)
from fmgs.query.index import EmbeddingIndex, IndexConfig, served_relevancy
from fmgs.query.plan import (
    EXACT_TABLE,
    FIRST_TIER,
    FIRST_TIER_AND_HEAD,
    NO_PASS,
    SECOND_TIER,
    choose_first_pass,
    union_rows,
)
from fmgs.query.reference import rank_reference, tier2_bounds_reference
from fmgs.query.state import build_state
from fmgs.query.tuning import TOP_SAMPLE_STEP
from fmgs.vecmath import safe_normalize

M, D = 6000, 96


@pytest.fixture(scope="module")
def scene():
    emb, copies = scene_embeddings(M, D, seed=4)
    canon_vecs = safe_normalize(torch.randn(4, D, generator=torch.Generator().manual_seed(5)))
    canon = emb @ canon_vecs.T
    return emb, copies, canon, canon_vecs, query_sets(emb, copies, 6)


_STATES: dict = {}
_REFERENCES: dict = {}


def _state(emb, cfg: IndexConfig | None = None, **kw):
    """build_state on the module's scene, once per setting: what EmbeddingIndex.build would build for
    ``cfg`` (or build_state(emb.half(), 16, **kw)). A state is data an index only reads, so every index
    built from it is still a fresh one (its own caches, the tuning in effect when it runs)."""
    args = (cfg.rank, cfg.basis_sample, cfg.rank2) if cfg is not None else (16,)
    key = (id(emb), args, tuple(sorted(kw.items())))
    if key not in _STATES or _STATES[key][0] is not emb:
        _STATES[key] = (emb, build_state(emb.half(), *args, **kw))
    return _STATES[key][1]


def _reference(emb, canon, q, k, threshold=None):
    """rank_reference(emb, canon, q, k[, threshold]), computed once per query: the float64 brute force is
    a pure function of its inputs, and the parametrised tests ask it the same questions on every path."""
    key = (id(emb), id(canon), q.numpy().tobytes(), k, threshold)
    if key not in _REFERENCES or _REFERENCES[key][0] is not emb or _REFERENCES[key][1] is not canon:
        kw = {} if threshold is None else {"threshold": threshold}
        _REFERENCES[key] = (emb, canon, rank_reference(emb, canon, q, k, **kw))
    return _REFERENCES[key][2]


def _indexes(emb, canon):
    """The paths on the same scene: the exact one (below exact_below), the compact one (two tiers), the
    compact one with its second tier split into a head and a tail, and the compact one with its first
    tier alone."""
    exact = EmbeddingIndex.build(emb, canon, IndexConfig(exact_below=M + 1))
    cfg = IndexConfig(rank=16, exact_below=M - 1, rerank=2)
    compact = EmbeddingIndex.build(emb.half(), canon, cfg, state=_state(emb, cfg))
    split = EmbeddingIndex.build(emb.half(), canon, cfg, state=_state(emb, head=32))
    t1cfg = IndexConfig(rank=16, rank2=0, exact_below=0, rerank=2)
    tier1 = EmbeddingIndex.build(emb.half(), canon, t1cfg, state=_state(emb, t1cfg))
    assert exact.exact and not compact.exact and compact.second_tier is not None and tier1.second_tier is None
    assert (
        compact.second_tier.tail is None
        and split.second_tier.tail is not None
        and split.second_tier.head == 32
    )
    return {"exact": exact, "compact": compact, "split": split, "tier1": tier1}


def _index(scene, path, monkeypatch):
    """The index for ``path``: "exact", "compact", "split" (its second tier as head and tail), "tier1" (no
    second tier), or a compact one with "-refined" (every rescoring set goes through the second tier and
    the float32 refinement first), "-direct" (texts take their first pass as the size of the scene would
    choose it were it large: the whole second tier, or the head for the split one, per text) or "-head"
    (every text's first pass through the first tier and the head)."""
    emb, _, canon, _, _ = scene
    if path.endswith("-refined"):
        monkeypatch.setattr(tuning, "REFINE_ABOVE", 0)
    if path.endswith(("-direct", "-head")):  # every text's first pass is over the second tier
        monkeypatch.setattr(tuning, "TIER2_FIRST_MIN_SAMPLE", 0)
        monkeypatch.setattr(tuning, "TIER2_FIRST_STEP", 64)
        monkeypatch.setattr(tuning, "TIER2_FIRST_FRACTION", -1.0)
    if path.endswith("-head"):
        monkeypatch.setattr(tuning, "HEAD_FRACTION", 2.0)
        monkeypatch.setattr(tuning, "HEAD_TEXTS", 1000)
    return _indexes(emb, canon)[path.split("-")[0]]


def _same(a, ref):
    """Same rows in the same order; scores equal up to the float32 rounding of float64 values that two
    summation orders can leave (one float32 step of the margin, amplified at most 2^4 by the sigmoid)."""
    assert torch.equal(a.rows, ref.rows)
    assert torch.allclose(a.similarity, ref.similarity, rtol=2**-23, atol=2**-40)
    assert torch.allclose(a.relevancy, ref.relevancy, rtol=2**-20, atol=0)


def test_query_sets_span_the_range(scene):
    emb, copies, *_, sets = scene
    best = {k: float((emb @ q.T).amax(0).median()) for k, q in sets.items()}
    assert best["near"] > 0.95 and 0.7 < best["typical"] < 0.95
    assert 0.2 <= best["clip"] <= 0.45 and best["absent"] < 0.35
    assert len(emb.unique(dim=0)) < M - len(copies) // 3  # exact copies: ties


@pytest.mark.parametrize(
    "path",
    [
        "exact",
        "compact",
        "compact-refined",
        "compact-direct",
        "split",
        "split-direct",
        "split-head",
        "tier1",
        "tier1-refined",
    ],
)
@pytest.mark.parametrize("k", [1, 7, 100, 1000, M])
def test_top_k_equals_brute_force_on_every_query_set(scene, path, k, monkeypatch):
    emb, _, canon, _, sets = scene
    idx = _index(scene, path, monkeypatch)
    for name in QUERY_SETS:
        for q in sets[name]:
            a = idx.rank(q, k)
            _same(a, _reference(emb, canon, q, k))
            assert k <= a.rescored <= M


@pytest.mark.parametrize("path", ["exact", "compact", "tier1"])
def test_ties_at_the_kth_place_break_by_row(scene, path):
    emb, copies, canon, _, _ = scene
    idx = _indexes(emb, canon)[path]
    # Rows with exact copies tie; cut the ranking at every place inside such a group.
    groups = 0
    for i in copies.tolist()[:40]:
        group = (emb == emb[i]).all(1).nonzero()[:, 0]
        if len(group) < 2:
            continue
        q = safe_normalize(emb[i][None])[0]
        full = _reference(emb, canon, q, M).rows
        pos = sorted(int((full == r).nonzero()[0, 0]) for r in group.tolist())
        assert pos == list(range(pos[0], pos[0] + len(group)))  # the copies sit together, by row
        for k in range(pos[0] + 1, pos[-1] + 2):
            _same(idx.rank(q, k), _reference(emb, canon, q, k))
        groups += 1
    assert groups >= 5


@pytest.mark.parametrize(
    "path", ["exact", "compact", "compact-refined", "compact-direct", "split-head", "tier1-refined"]
)
def test_threshold_queries_are_certified(scene, path, monkeypatch):
    emb, _, canon, _, sets = scene
    idx = _index(scene, path, monkeypatch)
    for name in ("clip", "typical", "absent"):
        for q in sets[name][:3]:
            ref_all = _reference(emb, canon, q, M)
            for thr in (0.05, float(ref_all.relevancy[min(50, M - 1)]), 0.5, 0.9, 1.0):
                a = idx.rank(q, M, threshold=thr)
                _same(a, _reference(emb, canon, q, M, thr))
                assert bool((a.relevancy >= thr).all())


@pytest.mark.parametrize(
    "path", ["exact", "compact", "compact-refined", "compact-direct", "split-head", "tier1-refined"]
)
def test_custom_canonical_and_batches(scene, path, monkeypatch):
    emb, _, canon, canon_vecs, sets = scene
    idx = _index(scene, path, monkeypatch)
    other = safe_normalize(torch.randn(3, D, generator=torch.Generator().manual_seed(8)))
    q = torch.cat([sets["clip"], sets["near"]])
    for cv, cdots in ((canon_vecs, canon), (other, emb @ other.T)):
        batch = idx.rank_many(q, 40, canonical_vectors=cv)
        for qi, a in zip(q, batch, strict=True):
            _same(a, rank_reference(emb, cdots, qi, 40))
    singles = [idx.rank(qi, 40) for qi in q]
    for a, b in zip(idx.rank_many(q, 40), singles, strict=True):
        _same(a, b)
        assert a.rescored == b.rescored


def test_refined_bounds_hold_and_damaged_rows_are_named(scene):
    emb, _, canon, _, sets = scene
    idx = _indexes(emb, canon)["compact"]
    q = sets["clip"][:1]
    rows = torch.arange(M)
    lo, up = (x[:, 0] for x in idx.half_rows.refine(rows, q, None))
    exact = emb.double() @ q[0].double() - canon.amax(1).double()
    assert bool((lo <= exact).all() and (exact <= up).all()) and float((up - lo).max()) < 1e-4
    assert torch.equal(idx.exact_dots(rows, q)[:, 0], idx.exact_dots(rows.flip(0), q)[:, 0].flip(0))
    bad = emb.half().clone()
    bad[17, 3] = float("inf")
    broken = EmbeddingIndex.build(bad, canon, IndexConfig(rank=16, exact_below=0))
    with pytest.raises(ValidationError, match="row 17 is not finite"):
        broken.half_rows.refine(rows, q, None)
    with pytest.raises(ValidationError, match="row 17 is not finite"):
        broken.exact_dots(rows, q)


def test_compact_bounds_hold_for_every_row(scene):
    emb, _, canon, _, sets = scene
    idx = _indexes(emb, canon)["compact"]
    q = torch.cat([sets[n] for n in QUERY_SETS])
    up = idx.compact.first_tier_upper(q).double()
    assert torch.equal(up, idx.upper_bounds(q).double())  # the index's cheap pass on the compact path
    exact = emb.double() @ q.double().T - canon.amax(1).double()[:, None]
    assert bool((up >= exact).all())
    slack = up - exact
    assert float(slack.min()) >= 0 and float(slack.median()) < 1.0


def test_second_tier_bounds_hold_are_tight_and_match_their_twin(scene):
    emb, _, canon, _, sets = scene
    idx = _indexes(emb, canon)["compact"]
    b = idx.compact
    t2 = idx.second_tier
    q = torch.cat([sets[n] for n in QUERY_SETS])
    rows = torch.arange(M)
    lo, up = b.tier2_bounds(rows, q)
    exact = (emb.double() @ q.double().T - canon.amax(1).double()[:, None]).T
    assert bool((lo <= exact).all() and (exact <= up).all())
    # Tighter than the first tier alone: the second tier is what settles CLIP-like queries.
    first = b.first_tier_upper(q).double().T - exact
    assert float((up - exact).median()) < float(first.median()) / 4
    # Against the float64 twin (the kernel sums in float32: within its slack).
    v64 = q.double()
    w1, w2 = v64 @ idx.state.basis.T, v64 @ t2.basis.T
    perp = v64 - w1 @ idx.state.basis - w2 @ t2.basis
    W1 = (v64 @ b.weighted_basis.T).float().numpy()
    W2 = (v64 @ b.weighted_basis2.T).float().numpy()
    rlo, rup = tier2_bounds_reference(
        idx.state.codes.numpy(), W1, t2.codes.numpy(), W2, *_no_tail(M, len(q)), rows.numpy(),
        idx.canonical_max.numpy(), b.err.numpy(), t2.bounds.numpy(), w1.norm(dim=1).numpy(),
        w2.norm(dim=1).numpy(), perp.norm(dim=1).numpy(), b.slack2,
    )  # fmt: skip
    assert np.allclose(lo.numpy(), rlo, rtol=0, atol=b.slack2) and np.allclose(up.numpy(), rup, atol=b.slack2)
    # Every row's upper bound alone, float32 rounded up (the direct first pass): never below the twin's.
    up32 = b.tier2_upper(q, torch.empty(len(q), M))
    assert bool((up32.double() >= exact).all())  # the bound holds on every row
    assert np.allclose(up32.double().numpy(), rup, rtol=0, atol=b.slack2)  # its twin, up to the float32 sum
    # Odd row subsets and one text (the kernel's single-text tail).
    sub = torch.arange(3, M, 7)
    lo1, up1 = b.tier2_bounds(sub, q[:1])
    assert torch.allclose(lo1[0], lo[0, sub], rtol=0, atol=1e-5) and torch.allclose(
        up1[0], up[0, sub], atol=1e-5
    )


def _no_tail(m: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """An empty third table and its weights (the kernels' twin for a tier stored whole, or a head alone)."""
    return np.zeros((m, 0), np.int8), np.zeros((n, 0), np.float32)


def test_split_second_tier_bounds_hold_and_match_the_whole_tier(scene):
    emb, _, canon, _, sets = scene
    ix = _indexes(emb, canon)
    split, whole = ix["split"].compact, ix["compact"].compact
    t2 = split.tier2
    q = torch.cat([sets[n] for n in QUERY_SETS])
    rows = torch.arange(M)
    exact = (emb.double() @ q.double().T - canon.amax(1).double()[:, None]).T
    # Head and tail together are the whole second tier: the same bounds up to the float32 sum's order.
    lo, up = split.tier2_bounds(rows, q)
    wlo, wup = whole.tier2_bounds(rows, q)
    assert bool((lo <= exact).all() and (exact <= up).all())
    assert torch.allclose(lo, wlo, rtol=0, atol=split.slack2) and torch.allclose(
        up, wup, rtol=0, atol=split.slack2
    )
    up32 = split.tier2_upper(q, torch.empty(len(q), M))
    assert bool((up32.double() >= exact).all()) and torch.allclose(
        up32.double(), wup, rtol=0, atol=split.slack2
    )
    # The head pass: every row's upper bound from the first tier and the head, never below the margin,
    # equal to its float64 twin up to the float32 sum, looser than the whole tier and tighter than the first.
    head = split.tier2_upper(q, torch.empty(len(q), M), head=True).double()
    assert bool((head >= exact).all())
    v64 = q.double()
    w1, w2 = v64 @ split.basis.T, v64 @ t2.basis[:32].T
    perp = v64 - w1 @ split.basis - w2 @ t2.basis[:32]
    _, rup = tier2_bounds_reference(
        split.codes.numpy(), (v64 @ split.weighted_basis.T).float().numpy(), t2.codes.numpy(),
        (v64 @ split.weighted_basis2[:32].T).float().numpy(), *_no_tail(M, len(q)), rows.numpy(),
        split.canonical_max.numpy(), split.err.numpy(), t2.head_bounds.numpy(), w1.norm(dim=1).numpy(),
        w2.norm(dim=1).numpy(), perp.norm(dim=1).numpy(), split.slack2,
    )  # fmt: skip
    assert np.allclose(head.numpy(), rup, rtol=0, atol=split.slack2)
    first = split.first_tier_upper(q).double().T
    assert float((head - exact).median()) < float((first - exact).median())
    assert float((head - exact).median()) > float((up - exact).median())


def test_texts_the_first_tier_cannot_settle_go_straight_to_the_second(scene, monkeypatch):
    emb, _, canon, _, sets = scene
    monkeypatch.setattr(tuning, "TIER2_FIRST_MIN_SAMPLE", 0)
    monkeypatch.setattr(tuning, "TIER2_FIRST_STEP", 64)  # a 94-row sample of this small scene
    ix = _indexes(emb, canon)
    idx = ix["compact"]
    q = torch.cat([sets[n] for n in QUERY_SETS])
    direct, head, _ = choose_first_pass(idx, q, 10, 40)
    assert head == []  # a second tier stored whole has no head pass
    chosen = set(direct)
    # explain reports the pass chosen (``first``, the rows rescored first, moves only the hints).
    want = [SECOND_TIER if j in chosen else FIRST_TIER for j in range(len(q))]
    assert [e.first_pass for e in idx.explain(q, 10)] == want
    # What the first tier actually leaves: the share of rows whose upper bound reaches the 10th margin.
    exact = emb.double() @ q.double().T - canon.amax(1).double()[:, None]
    left = (
        (idx.compact.first_tier_upper(q).double() >= torch.topk(exact, 10, dim=0).values[-1]).double().mean(0)
    )
    assert {j for j in range(len(q)) if left[j] > 0.8} <= chosen  # CLIP-like and absent: most rows left
    assert not {j for j in range(len(q)) if left[j] < 0.05} & chosen  # settled by the first tier
    # Each text of a mixed batch takes its own first pass; answers exact either way.
    for qi, a in zip(q, idx.rank_many(q, 10), strict=True):
        _same(a, _reference(emb, canon, qi, 10))
    # Split: the same texts leave the first tier; those whose head pass is estimated to leave at most
    # HEAD_FRACTION of the rows take it (all of them at 2, none at -1), the others the whole tier.
    split = ix["split"]
    monkeypatch.setattr(tuning, "HEAD_TEXTS", len(q))
    for frac, want_head in ((2.0, chosen), (-1.0, set())):
        monkeypatch.setattr(tuning, "HEAD_FRACTION", frac)
        direct, head, _ = choose_first_pass(split, q, 10, 40)
        assert set(head) == want_head and set(direct) | set(head) == chosen and not set(direct) & set(head)
    monkeypatch.setattr(tuning, "HEAD_FRACTION", 0.1)
    direct, head, _ = choose_first_pass(split, q, 10, 40)
    assert direct and head  # this scene's texts take all three passes
    want = [
        SECOND_TIER if j in direct else FIRST_TIER_AND_HEAD if j in head else FIRST_TIER
        for j in range(len(q))
    ]
    assert [e.first_pass for e in split.explain(q, 10)] == want
    # More texts leaving the first tier than HEAD_TEXTS: none takes the head pass.
    monkeypatch.setattr(tuning, "HEAD_TEXTS", len(chosen) - 1)
    assert choose_first_pass(split, q, 10, 40)[:2] == (sorted(chosen), [])
    monkeypatch.setattr(tuning, "HEAD_TEXTS", len(q))
    for qi, a in zip(q, split.rank_many(q, 10), strict=True):
        _same(a, _reference(emb, canon, qi, 10))


@pytest.mark.parametrize("path", ["exact", "compact", "compact-refined", "split-head", "tier1-refined"])
def test_explain_says_what_each_pass_left(scene, path, monkeypatch):
    """explain runs rank_many's passes and says, per text, the first pass and what each step left: the
    rows rescored first and those the second tier left add up to the answer's ``rescored``, and the rows
    scored exactly in all are the first ones and what the last step left."""
    sets = scene[4]
    idx = _index(scene, path, monkeypatch)
    q = torch.cat([sets[n] for n in QUERY_SETS])
    refined = 0
    for k in (1, 100):
        ranked, explained = idx.rank_many(q, k), idx.explain(q, k)
        assert len(explained) == len(q)
        for r, e in zip(ranked, explained, strict=True):
            assert e.rows == M and k <= e.first_rescored <= M
            assert e.first_pass == {"exact": EXACT_TABLE, "split-head": FIRST_TIER_AND_HEAD}.get(
                path, FIRST_TIER
            )
            if path.startswith(("exact", "tier1")):  # no second tier to narrow with
                assert e.left_by_second_tier is None
            left = e.left_by_first_pass if e.left_by_second_tier is None else e.left_by_second_tier
            assert left <= e.left_by_first_pass and e.first_rescored + left == r.rescored
            if e.left_by_refinement is None:
                assert e.scored_exactly == e.first_rescored + left
            else:
                assert e.scored_exactly == e.first_rescored + e.left_by_refinement
                refined += 1
    if path.endswith("-refined"):
        assert refined > 0
    assert [e.first_pass for e in idx.explain(q, 0)] == [NO_PASS] * len(q)


@pytest.mark.parametrize("hint", ["estimated", "above every row", "near the top", "below every row"])
def test_hinted_selections_keep_answers_exact(scene, monkeypatch, hint):
    """certify_start's hint (a cut estimated from the sample) replaces its scans when it holds the first
    candidates and every row reaching L, and costs one more scan when it does not: answers are exact
    either way."""
    emb, _, canon, _, sets = scene
    monkeypatch.setattr(tuning, "TIER2_FIRST_MIN_SAMPLE", 0)
    monkeypatch.setattr(tuning, "TIER2_FIRST_STEP", 64)
    q = torch.cat([sets[n] for n in QUERY_SETS])
    scans = []
    monkeypatch.setattr(certify_mod, "rows_at_least", lambda x, c: scans.append(c) or rows_at_least(x, c))
    exact = emb.double() @ q.double().T - canon.amax(1).double()[:, None]  # [M,n]
    if hint != "estimated":

        def forced(est, low, first, num):
            if hint == "near the top":  # above L: enough rows for the first candidates, not all of L's
                return torch.topk(exact, 2, dim=0).values[-1].numpy()
            return np.full(len(est), 1e30 if hint == "above every row" else -1e30)

        monkeypatch.setattr(plan_mod, "hints", forced)
    for name in ("compact", "split"):
        idx = _indexes(emb, canon)[name]
        for k in (1, 10, 300):
            scans.clear()
            for qi, a in zip(q, idx.rank_many(q, k), strict=True):
                _same(a, _reference(emb, canon, qi, k))
            if hint == "below every row":  # one scan per text, which keeps every row
                assert scans == [-1e30] * len(q)
            if hint == "above every row":  # the hint's scan, then the text's own two
                assert len(scans) >= 2 * len(q)
            if hint == "near the top" and k > 1:  # L falls below the hint: a second scan for L
                assert len(scans) > len(q)
    if hint == "estimated":  # one scan per text on this scene (k = 300)
        assert len(scans) == len(q)


def test_certified_top_k_with_loose_bounds_is_still_exact():
    g = torch.Generator().manual_seed(0)
    m = torch.randn(2000, generator=g, dtype=torch.float64)
    m[100:110] = m[5]  # ties
    for width in (0.0, 0.01, 1.0, 100.0):
        up = (m + width * torch.rand(2000, generator=g, dtype=torch.float64)).float() + 1e-6
        for k in (1, 10, 105, 2000):
            order = sorted(range(2000), key=lambda i: (-float(m[i]), i))[:k]
            c = certified_top_k(up, k, lambda r: m[r], first=k)
            assert c.rows.tolist() == order
            assert k <= c.rescored <= 2000
            # With a refinement stage of bounds tighter than the first (and as loose as 0.1).
            w = torch.rand(2000, generator=g, dtype=torch.float64) * min(width, 0.1)
            c = certified_top_k(
                up,
                k,
                lambda r: m[r],
                first=k,
                refine=lambda r, w=w: (m[r] - w[r], m[r] + w[r]),
                refine_above=0,
            )
            assert c.rows.tolist() == order
            # Chained tiers: a looser superset narrows first (certify_narrow), then a tighter refinement.
            p = certify_start(up, k, lambda r: m[r], first=k)
            rows = torch.arange(0, 2000)
            w2 = torch.rand(2000, generator=g, dtype=torch.float64) * min(width, 0.5)
            p2 = certify_narrow(p, k, Refined(rows, m - w2, m + w2))
            assert p2.bound >= p.bound and p2.n2 <= p.n2 and set(p2.rows2.tolist()) <= set(p.rows2.tolist())
            assert bool((p2.rows2[1:] > p2.rows2[:-1]).all())
            c = certify_finish(p2, k, lambda r: m[r], refined=Refined(rows, m - w, m + w))
            assert c.rows.tolist() == order


def test_threshold_margin_never_drops_a_passing_row():
    rng = np.random.default_rng(0)
    for thr in (1e-30, 1e-6, 0.3, 0.5, 0.731, 0.999, 0.9999999, 1.0):
        mm = threshold_margin(thr, served_relevancy)
        assert math.isfinite(mm) or thr >= 1.0
        m = torch.from_numpy(rng.normal(mm if math.isfinite(mm) else 0, 1e-3, 20000).astype(np.float32))
        passing = served_relevancy(m) >= thr
        assert bool((m[passing].double() > mm).all())
    assert threshold_margin(0.0, served_relevancy) == -math.inf


def test_state_norms_bound_the_decomposition():
    emb, _ = scene_embeddings(3000, 64, seed=1)
    st = build_state(emb.half(), 8)
    c = emb.double() @ st.basis.T
    deq = st.codes.double() * st.scales.double()
    assert bool(((c - deq).norm(dim=1) <= st.err_norm.double()).all())
    assert bool(((emb.double() - c @ st.basis).norm(dim=1) <= st.res_norm.double()).all())
    assert torch.allclose(st.basis @ st.basis.T, torch.eye(8, dtype=torch.float64), atol=1e-12)
    # The second tier: up to the numerical rank (64 here: full), orthonormal to the first.
    t2 = st.tier2
    assert t2 is not None and t2.rank == 63 - 8
    both = torch.cat([st.basis, t2.basis])
    assert torch.allclose(both @ both.T, torch.eye(63, dtype=torch.float64), atol=1e-12)
    c2 = emb.double() @ t2.basis.T
    assert bool(((c2 - t2.codes.double() * t2.scales.double()).norm(dim=1) <= t2.bounds[:, 0].double()).all())
    assert bool(((emb.double() - c @ st.basis - c2 @ t2.basis).norm(dim=1) <= t2.bounds[:, 1].double()).all())
    # A scene of low rank: the second tier stops at its numerical rank.
    low = safe_normalize(
        torch.randn(3000, 20, generator=torch.Generator().manual_seed(3)) @ torch.randn(20, 64)
    )
    st = build_state(low.half(), 8)
    assert st.tier2 is not None and st.rank + st.tier2.rank == 24  # rank 20, rounded up to a multiple of 8
    assert float(st.tier2.bounds[:, 1].max()) < 1e-2  # what remains is float16 rounding
    assert build_state(low.half(), 8, rank2=0).tier2 is None


def test_top_rows_selects_the_largest_values_like_topk():
    """The sampled selector returns n rows whose values are topk's values (ties at the cut may pick other
    rows of the same value), sorted, on smooth, tied, adversarial (the sample sees only small values) and
    small inputs."""
    g = torch.Generator().manual_seed(5)
    M = 200_000
    smooth = torch.randn(M, generator=g)
    tied = torch.randint(0, 50, (M,), generator=g).float()  # thousands of rows per value
    hidden = torch.zeros(M)
    hidden[torch.arange(M) % TOP_SAMPLE_STEP != 0] = torch.rand(M - M // TOP_SAMPLE_STEP, generator=g) + 1
    cases = [(smooth, n) for n in (1, 7, 100, 781, 3000, M // 8)] + [(tied, n) for n in (1, 100, 2500)]
    spiked = torch.zeros(M)  # the sample sees only large values: too few candidates, full selection
    spiked[::TOP_SAMPLE_STEP] = torch.rand(len(spiked[::TOP_SAMPLE_STEP]), generator=g) + 1
    cases += [(hidden, 100), (spiked, 100), (smooth[:500], 20), (smooth, M), (smooth, M // 2)]
    for x, n in cases:
        rows = top_rows(x, n)
        twin = torch.topk(x, n, sorted=False).values.sort().values
        assert len(rows) == n and len(torch.unique(rows)) == n
        assert bool((rows[1:] > rows[:-1]).all())
        assert torch.equal(x[rows].sort().values, twin)


def test_certify_start_reuses_the_candidates_only_when_they_hold_every_row_left():
    """Rows still to settle are every row whose bound reaches L, not yet scored: taken from top_rows'
    candidates when L is at or above their cut, from a pass over every row otherwise (exact margins far
    below, near and at the bounds; tied, spiked and NaN bounds)."""
    g = torch.Generator().manual_seed(6)
    M = 100_000
    smooth = torch.randn(M, generator=g, dtype=torch.float64)
    tied = torch.randint(0, 40, (M,), generator=g).double()
    spiked = torch.zeros(M, dtype=torch.float64)
    spiked[::TOP_SAMPLE_STEP] = 1 + torch.rand(-(-M // TOP_SAMPLE_STEP), generator=g, dtype=torch.float64)
    holed = smooth.clone()
    holed[::97] = float("nan")
    for up in (smooth, tied, spiked, holed):
        for gap in (0.0, 1e-3, 0.5, 3.0):  # exact margins this far below the bounds
            for k, first in ((1, 40), (10, 400), (100, 100)):
                p = certify_start(up, k, lambda r, up=up, gap=gap: up[r] - gap, first=first)
                want = _drop_sorted(rows_at_least(up, p.bound), p.rows1)
                assert torch.equal(p.rows2, want)


@pytest.mark.parametrize("room", [1 << 15, 64])  # 64: most selections overflow the kernel's buffer
def test_sorted_row_helpers_match_set_operations(monkeypatch, room):
    """rows_at_least against torch.nonzero in float64 (ties at the cut, cuts between two float32 values,
    NaN never selected, float64 and strided input too, a length that is not a multiple of the kernel's
    lanes); the sorted difference and intersection against Python sets, empty and disjoint inputs
    included."""
    monkeypatch.setattr(tuning, "SELECT_ROOM", room)
    g = torch.Generator().manual_seed(11)
    x = torch.randint(0, 20, (5003,), generator=g).float()
    x[::97] = float("nan")
    x[5] = 7.0 + 2.0**-20  # the float32 just above 7 (a cut between them keeps it and not 7)
    for cut in (-1.0, 0.0, 7.0, 7.0 + 1e-9, 7.0 - 1e-9, 19.0, 20.0, float("nan"), -math.inf):
        for v in (x, x.double(), x[::2]):
            want = torch.nonzero(v.double() >= cut).reshape(-1)
            assert torch.equal(rows_at_least(v, cut), want)
    for na, nb in ((0, 0), (0, 10), (10, 0), (300, 50), (50, 300), (2000, 2000)):
        a = torch.randperm(4000, generator=g)[:na].sort().values
        b = torch.randperm(4000, generator=g)[:nb].sort().values
        sa, sb = set(a.tolist()), set(b.tolist())
        assert _drop_sorted(a, b).tolist() == sorted(sa - sb)
        assert _keep_sorted(a, b).tolist() == sorted(sa & sb)
    a = torch.arange(0, 100, 2)
    assert torch.equal(_drop_sorted(a, torch.arange(1, 100, 2)), a)  # disjoint
    assert len(_keep_sorted(a, torch.arange(1, 100, 2))) == 0


def test_union_of_pending_rows_both_ways():
    """union_rows by sorting short lists and by a mask over the rows when they are long: the same sorted
    set."""
    g = torch.Generator().manual_seed(12)
    e = torch.zeros(0)
    for num, size in ((100_000, 50), (100_000, 40_000), (1000, 999)):
        ps = [Pending(e, e, 0.0, torch.randperm(num, generator=g)[:size].sort().values) for _ in range(4)]
        want = sorted(set().union(*(set(p.rows2.tolist()) for p in ps)))
        for texts in ([0], [1, 3], [0, 1, 2, 3]):
            got = union_rows(ps, texts, num)
            assert got.tolist() == sorted(set().union(*(set(ps[j].rows2.tolist()) for j in texts)))
        assert union_rows(ps, [0, 1, 2, 3], num).tolist() == want


def test_second_tier_sample_holds_the_strided_rows(scene, monkeypatch):
    emb, _, canon, _, _ = scene
    idx = _indexes(emb, canon)["compact"]
    b = idx.compact
    s, rows = b.sample, torch.arange(0, M, tuning.TIER2_FIRST_STEP)
    assert np.array_equal(s.first_codes, idx.state.codes[rows].numpy())
    assert np.array_equal(s.head_codes, idx.second_tier.codes[rows].numpy())
    assert np.array_equal(s.tier2_norms, idx.second_tier.bounds[rows].numpy())
    assert np.array_equal(s.shift, idx.canonical_max[rows].numpy())
    assert np.array_equal(s.first_err, b.err[rows].numpy()) and np.array_equal(
        s.first_res, b.res[rows].numpy()
    )
    assert s.tail_codes.shape == (len(rows), 0) and s.head_norms.shape == (len(rows), 0)  # stored whole
    split = _indexes(emb, canon)["split"]
    t = split.compact.sample
    assert np.array_equal(t.tail_codes, split.second_tier.tail[rows].numpy())
    assert np.array_equal(t.head_norms, split.second_tier.head_bounds[rows].numpy())
    # Counted as resident where the estimate runs (scenes of TIER2_FIRST_MIN_SAMPLE sample rows or more).
    without = idx.nbytes()
    monkeypatch.setattr(tuning, "TIER2_FIRST_MIN_SAMPLE", 0)
    assert idx.nbytes() - without == sum(a.nbytes for a in s)


@pytest.mark.parametrize(
    "cfg", [IndexConfig(exact_below=10**9), IndexConfig(rank=4, exact_below=0, rerank=2)]
)
@pytest.mark.parametrize("seed", [1, 3])
def test_float32_copies_tie_exactly_whatever_rows_are_scored_with_them(cfg, seed):
    # Float32 input (the Python API's, not a package's float16): a row's exact margin must not depend on
    # the batch it is rescored in, or equal rows stop tying and the order is no longer by row.
    g = torch.Generator().manual_seed(seed)
    emb = safe_normalize(torch.randn(1, 32, generator=g)).repeat(500, 1)
    emb[::7] = safe_normalize(torch.randn(1, 32, generator=g))
    canon = emb @ safe_normalize(torch.randn(3, 32, generator=g)).T
    idx = EmbeddingIndex.build(emb, canon, cfg)
    d = idx.exact_dots(torch.arange(500), emb[1:2])
    assert len(d[emb[:, 0] == emb[1, 0]].unique()) == 1
    for rows in (torch.arange(7), torch.tensor([499, 1]), torch.arange(3, 400, 3)):
        assert torch.equal(idx.exact_dots(rows, emb[1:2]), d[rows])
    for q in (emb[1], emb[0], safe_normalize(torch.randn(1, 32, generator=g))[0]):
        for k in (1, 7, 100, 430, 500):
            _same(idx.rank(q, k), rank_reference(emb, canon, q, k))
