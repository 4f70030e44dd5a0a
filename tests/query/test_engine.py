"""The query engine: compact index against the exact ranking, instances, pose/point/segment queries."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fmgs.errors import ValidationError
from fmgs.query.engine import EngineConfig, SceneEngine
from fmgs.query.index import EmbeddingIndex, IndexConfig
from fmgs.query.instances import InstanceConfig, dbscan
from fmgs.query.points import NoFieldError, query_points
from fmgs.query.pose import render_pose, render_pose_reference
from fmgs.query.reference import int8_dots_reference, rank_reference
from fmgs.query.segment import segment
from fmgs.scene.package import load_scene
from fmgs.vecmath import safe_normalize
from tests.helpers.query_scenes import CENTRES, D, blob_scene, camera


def _scene(tmp_path, with_field=False, name="s"):
    return blob_scene(tmp_path / name, with_field)


def _camera():
    return camera()


def test_mmap_load_equals_memory_load(tmp_path):
    p, *_ = _scene(tmp_path)
    a, b = load_scene(p), load_scene(p, mmap=True)
    assert b.embeddings.dtype == torch.float16
    assert torch.equal(a.embeddings, b.embeddings.float())


@pytest.mark.parametrize("rerank", [0, 4])
def test_compact_index_against_exact_ranking(rerank):
    g = torch.Generator().manual_seed(1)
    M, r = 5000, 8
    basis = safe_normalize(torch.randn(r, 64, generator=g))
    emb = safe_normalize(torch.randn(M, r, generator=g) @ basis + 0.02 * torch.randn(M, 64, generator=g))
    canon = emb @ safe_normalize(torch.randn(4, 64, generator=g)).T
    cfg = IndexConfig(rank=12, exact_below=0, rerank=rerank)
    idx = EmbeddingIndex.build(emb, canon, cfg)
    assert not idx.exact and idx.state.codes.shape == (M, 12)
    for _ in range(20):
        q = safe_normalize(torch.randn(64, generator=g) @ torch.eye(64))
        q = safe_normalize(q[None] @ basis.T @ basis + 0.05 * q[None])[0]
        fast, ref = idx.rank(q, 50), rank_reference(emb, canon, q, 50)
        assert torch.equal(fast.rows, ref.rows)  # certified: exact whatever the initial candidates
        assert torch.equal(fast.similarity, ref.similarity)
        assert 50 <= fast.rescored < M


def test_exact_index_equals_reference_and_threshold(tmp_path):
    p, classes, _ = _scene(tmp_path)
    eng = SceneEngine.open(p)
    assert eng.index.exact
    pkg = load_scene(p)
    for c in classes:
        a = eng.text_query(c, 40)
        ref = rank_reference(pkg.embeddings, pkg.canonical, c, 40)
        assert torch.equal(a.index, pkg.selected[ref.rows])
        assert torch.allclose(a.relevancy, ref.relevancy)
        t = float(a.relevancy[10])
        b = eng.text_query(c, 40, threshold=t)
        assert len(b.index) >= 11 and bool((b.relevancy >= t).all())


def test_query_ranks_the_right_blob_and_instances(tmp_path):
    p, classes, _ = _scene(tmp_path)
    eng = SceneEngine.open(p)
    for i, c in enumerate(classes):
        a = eng.text_query(c, 60, instances=InstanceConfig(min_points=5))
        blob = (a.index // 60 == i).float().mean()
        assert blob > 0.9
        assert len(a.instances) >= 1
        top = a.instances[0]
        assert np.linalg.norm(top.centroid - CENTRES[i].numpy()) < 0.1
        pts = eng.gaussians.means[a.index[top.members]].double().numpy()
        for box in (top.aabb, top.obb):
            R = box.rotation
            assert np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0
            local = (pts - box.center) @ R
            assert (np.abs(local) <= box.extent / 2 + 1e-9).all()
        assert (a.instance_ids[top.members] == 0).all()


def test_custom_canonical_phrases(tmp_path):
    p, classes, canon = _scene(tmp_path)
    eng = SceneEngine.open(p)
    same = eng.text_query(classes[0], 30, canonical=canon)
    ref = eng.text_query(classes[0], 30)
    assert torch.equal(same.index, ref.index)
    assert torch.allclose(same.relevancy, ref.relevancy, atol=1e-5)
    with pytest.raises(ValidationError, match="canonical"):
        eng.text_query(classes[0], 5, canonical=torch.zeros(2, D))


def _dbscan_brute(p, eps, min_pts):
    n = len(p)
    d = np.linalg.norm(p[:, None] - p[None], axis=-1)
    nb = d <= eps
    core = nb.sum(1) >= min_pts
    lab = np.full(n, -1)
    c = 0
    for i in range(n):  # flood fill over core points in index order
        if core[i] and lab[i] == -1:
            stack, lab[i] = [i], c
            while stack:
                j = stack.pop()
                for k in np.flatnonzero(nb[j] & core):
                    if lab[k] == -1:
                        lab[k] = c
                        stack.append(k)
            c += 1
    for i in np.flatnonzero(~core):
        cand = np.flatnonzero(nb[i] & core)
        if len(cand):
            lab[i] = lab[cand[np.argmin(d[i, cand])]]
    return lab


@pytest.mark.parametrize("seed", range(5))
def test_dbscan_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    p = np.concatenate(
        [rng.normal(c, 0.1, (40, 3)) for c in rng.uniform(-2, 2, (4, 3))] + [rng.uniform(-3, 3, (30, 3))]
    )
    assert np.array_equal(dbscan(p, 0.25, 5), _dbscan_brute(p, 0.25, 5))


def test_dbscan_refuses_more_neighbour_pairs_than_it_holds_before_listing_them(monkeypatch):
    """A radius that puts every point near every other (a client's instances.eps, or a dense object in
    a large top_k) would list all n(n-1)/2 pairs at once: a server's memory ran out instead of an error."""
    import scipy.spatial

    listed = []

    class Tree(scipy.spatial.cKDTree):
        def query_pairs(self, *a, **k):
            listed.append(1)
            return super().query_pairs(*a, **k)

    monkeypatch.setattr(scipy.spatial, "cKDTree", Tree)
    p = np.random.default_rng(0).normal(0, 0.1, (100, 3))  # 4950 pairs within eps 1e12
    with pytest.raises(ValidationError, match=r"instances: 4950 pairs .* instances\.eps or top_k"):
        dbscan(p, 1e12, 5, max_pairs=1000)
    assert not listed
    assert (dbscan(p[:45], 1e12, 5, max_pairs=1000) == 0).all() and listed  # 990 pairs: grouped as before
    with pytest.raises(ValidationError, match="max_pairs"):
        InstanceConfig(max_pairs=0)


def test_pose_relevancy_equals_full_feature_render(tmp_path):
    p, classes, _ = _scene(tmp_path)
    eng = SceneEngine.open(p)
    pkg = load_scene(p)
    cam = _camera()
    out = render_pose(eng, cam, classes[1], ("relevancy", "rgb", "depth", "alpha"))
    ref = render_pose_reference(eng, cam, classes[1], pkg.embeddings)
    assert out.relevancy.shape == (40, 48) and out.rgb.shape == (40, 48, 3)
    assert torch.isfinite(out.relevancy).all() and torch.isfinite(out.depth).all()
    assert (out.relevancy - ref).abs().max() < 1e-4
    x, y, v = out.argmax
    assert v == float(out.relevancy.max()) and out.relevancy[y, x] == v
    assert out.alpha.max() > 0.5 and (out.depth[out.alpha > 0.5] > 3).all()
    only = render_pose(eng, cam, None, ("rgb",))
    assert only.relevancy is None and only.alpha is None and torch.equal(only.rgb, out.rgb)
    with pytest.raises(ValidationError, match="text"):
        render_pose(eng, cam, None, ("relevancy",))
    with pytest.raises(ValidationError, match="outputs"):
        render_pose(eng, cam, classes[0], ("normals",))


def test_segmentation_labels(tmp_path):
    p, classes, _ = _scene(tmp_path)
    eng = SceneEngine.open(p)
    s = segment(eng, classes, _camera(), per_gaussian=True)
    truth = (s.gaussian_index // 60).to(torch.int32)
    assert (s.gaussian_labels == truth).float().mean() > 0.95
    assert s.pixel_labels.shape == (40, 48) and set(s.pixel_labels.unique().tolist()) <= {-1, 0, 1, 2}
    assert (s.pixel_labels >= 0).any() and (s.pixel_labels == -1).any()


def test_point_query_through_the_field(tmp_path):
    p, classes, canon = _scene(tmp_path, with_field=True)
    eng = SceneEngine.open(p)
    pts = eng.gaussians.means[:10]
    a = query_points(eng, pts, classes, canon)
    f = eng.field(pts).clip
    assert a.relevancy.shape == (3, 10)
    assert torch.allclose(a.similarity, classes @ f.T, atol=1e-5)
    far = query_points(eng, torch.tensor([[1e9, -1e9, 0.0]]), classes, canon)
    assert torch.isfinite(far.relevancy).all()
    with pytest.raises(ValidationError, match="points"):
        query_points(eng, torch.tensor([[0.0, float("nan"), 0.0]]), classes, canon)
    q, *_ = _scene(tmp_path, name="nofield")
    with pytest.raises(NoFieldError, match="no feature field"):
        query_points(SceneEngine.open(q), pts, classes, canon)


def test_point_queries_in_chunks_equal_one_pass_and_can_be_stopped(tmp_path):
    p, classes, canon = _scene(tmp_path, with_field=True)
    eng = SceneEngine.open(p)
    g = torch.Generator().manual_seed(4)
    pts = eng.gaussians.means[:50] + 0.05 * torch.randn(50, 3, generator=g)
    whole = query_points(eng, pts, classes, canon, chunk=1000)
    calls = []
    parts = query_points(eng, pts, classes, canon, chunk=7, between_chunks=lambda: calls.append(1))
    assert len(calls) == 8  # ceil(50 / 7)
    assert torch.allclose(parts.similarity, whole.similarity, atol=1e-6)
    assert torch.allclose(parts.relevancy, whole.relevancy, atol=1e-6)

    def stop():
        raise TimeoutError("deadline")

    with pytest.raises(TimeoutError):
        query_points(eng, pts, classes, canon, chunk=7, between_chunks=stop)
    with pytest.raises(ValidationError, match="chunk"):
        query_points(eng, pts, classes, canon, chunk=0)


def test_query_state_bytes_per_gaussian():
    g = torch.Generator().manual_seed(0)
    M = 20000
    emb = safe_normalize(torch.randn(M, 512, generator=g)).half()
    canon = torch.randn(M, 4, generator=g)
    idx = EmbeddingIndex.build(emb, canon, IndexConfig(rank=32, rank2=0, exact_below=0))
    per = (
        idx.nbytes() - idx.state.basis.numel() * 8 - idx.state.scales.numel() * 4
    ) / M + 8  # + int64 scene index
    assert per <= 32 + 12 + 8, per  # codes, two bound norms and the canonical maximum, scene index
    # A second tier built in memory (no stored state to map) is resident, and counted.
    two = EmbeddingIndex.build(emb, canon, IndexConfig(rank=32, rank2=256, exact_below=0))
    assert two.second_tier is not None and not two.second_tier.mapped and two.second_tier.rank == 256 - 32
    small = (
        two.state.basis.numel() * 8
        + two.state.scales.numel() * 4
        + two.second_tier.basis.numel() * 8
        + 224 * 4
    )
    assert two.second_tier.head == 128 and two.second_tier.tail.shape[1] == 224 - 128
    assert two.nbytes() - small == M * (32 + 12 + 224 + 8 + 8)  # ... and the head's two norms


def test_engine_config_rejects_nonsense():
    with pytest.raises(ValueError):
        IndexConfig(rank=-1)
    with pytest.raises(ValidationError):
        InstanceConfig(eps=float("nan"))
    assert EngineConfig().backend == "auto"


def test_int8_kernel_matches_reference():
    g = torch.Generator().manual_seed(3)
    emb = safe_normalize(torch.randn(3000, 48, generator=g))
    idx = EmbeddingIndex.build(emb, torch.randn(3000, 4, generator=g), IndexConfig(rank=24, exact_below=0))
    assert idx.state.codes.dtype == torch.int8 and idx.state.scales.shape == (24,)
    v = safe_normalize(torch.randn(5, 48, generator=g))
    fast = idx.dots(v)
    ref = int8_dots_reference(idx.state.codes, idx.state.scales, idx.state.basis, v)
    assert (fast - ref).abs().max() < 1e-5
    shift = torch.randn(3000, generator=g)
    assert (idx.dots(v, shift) - (ref - shift[:, None])).abs().max() < 1e-5
    # The upper-bound kernel (four queries per sweep from 4 on, a tail after) against the same twin.
    for n in (1, 3, 4, 7, 8):
        w = safe_normalize(torch.randn(n, 48, generator=g))
        up = idx.compact.first_tier_upper(w).double()
        r = int8_dots_reference(idx.state.codes, idx.state.scales, idx.state.basis, w).double()
        _, wn, vn = idx.compact.first_tier_weights(w)
        err, res = idx.compact.err.double()[:, None], idx.compact.res.double()[:, None]
        terms = err * wn.double()[None] + res * vn.double()[None]
        want = r - idx.canonical_max.double()[:, None] + terms + idx.compact.slack
        assert up.shape == (3000, n) and (up - want).abs().max() < 1e-5, n
    # Quantisation error against the unquantised rank-24 projection stays at the int8 step size.
    proj = ((emb.double() @ idx.state.basis.T) @ (v.double() @ idx.state.basis.T).T).float()
    assert (ref - proj).abs().max() < 24 * float(idx.state.scales.max()) / 2


def test_relevancy_channels_cache_is_exact_and_bounded(tmp_path):
    p, classes, canon = _scene(tmp_path)
    eng = SceneEngine.open(p)
    first = eng.relevancy_channels(classes[0]).clone()
    assert torch.equal(eng.relevancy_channels(classes[0]), first)
    assert torch.equal(first, torch.cat([eng.channels(eng.unit(classes[0][None])), eng.index.canonical], 1))
    other = eng.relevancy_channels(classes[0], canon[:2])
    assert other.shape == (eng.num_embedded, 3)
    for i in range(20):
        eng.relevancy_channels(safe_normalize(torch.randn(D, generator=torch.Generator().manual_seed(i))))
    assert len(eng._chan_cache) == eng.CHANNEL_CACHE


def test_gaussian_columns_are_activated_attributes(tmp_path):
    p, _, _ = _scene(tmp_path)
    e = SceneEngine(load_scene(p, mmap=False))
    g = e.gaussians
    g.quats[3] = 0.0  # a zero quaternion answers the identity rotation, never NaN
    idx = torch.tensor([3, 0, 7])
    cols = e.gaussian_columns(idx, ["mean", "opacity", "scale", "rotation", "color"])
    assert all(c.dtype == np.float32 and len(c) == 3 for c in cols.values())
    assert np.array_equal(cols["mean"], g.means[idx].float().numpy())
    assert np.allclose(cols["opacity"], torch.sigmoid(g.opacity_logits[idx]).numpy())
    assert np.allclose(cols["scale"], torch.exp(g.log_scales[idx]).numpy())
    assert np.array_equal(cols["rotation"][0], [1.0, 0.0, 0.0, 0.0])
    assert np.allclose(np.linalg.norm(cols["rotation"], axis=1), 1.0, atol=1e-6)
    assert cols["color"].min() >= 0.0 and cols["color"].max() <= 1.0
    assert e.gaussian_columns(idx, []) == {}
    with pytest.raises(ValidationError, match="nope"):
        e.gaussian_columns(idx, ["nope"])


def test_warm_up_runs_the_first_request_kernels_and_leaves_no_cache(tmp_path):
    p, classes, _ = _scene(tmp_path)
    eng = SceneEngine.open(p)
    assert eng.warm_up() >= 0.0
    assert len(eng._chan_cache) == 0
    a = eng.text_query(classes[0], 5)
    assert len(a.index) == 5
