"""Spatial shards: the split, the shard packages, and sharded text answers equal to the unsharded ones."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from benchmarks.query_sets import QUERY_SETS, query_sets, scene_embeddings
from fmgs.errors import ValidationError
from fmgs.gaussians import GaussianSet
from fmgs.query.engine import EngineConfig, SceneEngine
from fmgs.query.index import IndexConfig
from fmgs.query.instances import InstanceConfig
from fmgs.query.sharded import ShardedScene
from fmgs.scene.package import export_scene, load_scene
from fmgs.scene.shards import SHARDS_FILE, ShardManifest, kd_split, read_shard_ids, write_shards
from fmgs.vecmath import safe_normalize

N, M, D = 5000, 4000, 64
COLUMNS = ("mean", "opacity", "scale", "rotation", "color")


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """A package of N Gaussians (M embedded, with exact and near copies: ties) and its query sets."""
    g = torch.Generator().manual_seed(3)
    means = torch.rand(N, 3, generator=g) * torch.tensor([4.0, 2.0, 1.0])
    sel = torch.sort(torch.randperm(N, generator=g)[:M]).values
    emb, copies = scene_embeddings(M, D, seed=7, means=means[sel])
    gs = GaussianSet(
        means,
        torch.randn(N, 4, generator=g),
        torch.randn(N, 3, generator=g) - 3,
        torch.randn(N, generator=g),
        torch.randn(N, 1, 3, generator=g),
    )
    canon = safe_normalize(torch.randn(4, D, generator=g))
    root = tmp_path_factory.mktemp("shards")
    path = export_scene(root / "src", gs, sel, emb, "test/enc", canon, query_rank=16)
    sets = query_sets(emb, copies, 3)
    negs = safe_normalize(torch.randn(12, D, generator=g))
    return root, path, sets, negs


def test_kd_split_is_balanced_reproducible_and_inside_its_cells():
    pts = np.random.default_rng(0).normal(size=(1001, 3))
    pts[:50] = pts[50]  # a stack of equal points straddles a cut
    for k in (1, 2, 3, 4, 7, 8):
        cells, boxes = kd_split(pts, k)
        sizes = [len(c) for c in cells]
        assert sum(sizes) == len(pts) and max(sizes) - min(sizes) <= k
        assert np.array_equal(np.sort(np.concatenate(cells)), np.arange(len(pts)))
        for c, b in zip(cells, boxes, strict=True):
            assert (pts[c] >= b[:3]).all() and (pts[c] <= b[3:]).all()
        again, _ = kd_split(pts, k)
        assert all(np.array_equal(a, b) for a, b in zip(cells, again, strict=True))
    with pytest.raises(ValidationError, match="shards"):
        kd_split(pts[:3], 4)
    with pytest.raises(ValidationError, match="shards"):
        kd_split(pts, 0)


def test_each_shard_is_a_valid_package_holding_the_source_bits(source, tmp_path):
    _, path, *_ = source
    out = write_shards(path, tmp_path / "sharded", 4)
    sm = ShardManifest.read(out)
    src = load_scene(path)
    seen_g, seen_r = [], []
    for info in sm.shards:
        p = load_scene(out / info.folder)
        gi, rows = read_shard_ids(out / info.folder, info.num_gaussians, info.num_selected)
        assert torch.equal(p.gaussians.means, src.gaussians.means[gi])
        assert torch.equal(p.embeddings, src.embeddings[rows])
        assert torch.equal(p.canonical, src.canonical[rows])
        assert torch.equal(gi[p.selected], src.selected[rows])
        assert p.query_state is not None  # stored, so the shard opens without rebuilding it
        seen_g.append(gi)
        seen_r.append(rows)
    assert torch.equal(torch.sort(torch.cat(seen_g)).values, torch.arange(N))
    assert torch.equal(torch.sort(torch.cat(seen_r)).values, torch.arange(M))
    assert (sm.num_gaussians, sm.num_selected) == (N, M)


def test_a_damaged_shard_manifest_is_refused_with_its_path(source, tmp_path):
    _, path, *_ = source
    out = write_shards(path, tmp_path / "sharded", 2)
    m = json.loads((out / SHARDS_FILE).read_text())
    m["shards"][0]["counts"]["gaussians"] += 1
    (out / SHARDS_FILE).write_text(json.dumps(m))
    with pytest.raises(ValidationError, match="add up"):
        ShardManifest.read(out)
    (out / SHARDS_FILE).write_text("{")
    with pytest.raises(ValidationError, match=SHARDS_FILE):
        ShardManifest.read(out)


def _same_answer(a, b):
    assert torch.equal(a.index, b.index)
    assert torch.equal(a.relevancy, b.relevancy)
    assert torch.equal(a.similarity, b.similarity)
    assert a.presence == b.presence
    assert len(a.instances) == len(b.instances)
    for x, y in zip(a.instances, b.instances, strict=True):
        assert np.array_equal(x.centroid, y.centroid) and x.score == y.score
        assert np.array_equal(x.members, y.members)
        for bx, by in ((x.aabb, y.aabb), (x.obb, y.obb)):
            assert all(np.array_equal(u, v) for u, v in zip(bx, by, strict=True))
    assert (a.instance_ids is None) == (b.instance_ids is None)
    if a.instance_ids is not None:
        assert np.array_equal(a.instance_ids, b.instance_ids)


@pytest.mark.parametrize("path_kind", ["exact", "compact"])
@pytest.mark.parametrize("k_shards", [2, 4, 8])
def test_sharded_text_answers_equal_the_unsharded_bit_for_bit(source, tmp_path, path_kind, k_shards):
    _, path, sets, negs = source
    icfg = IndexConfig(rank=16, exact_below=M + 1 if path_kind == "exact" else 100, rerank=2)
    cfg = EngineConfig(icfg)
    whole = SceneEngine.open(path, cfg)
    sharded = ShardedScene(write_shards(path, tmp_path / f"s{k_shards}", k_shards), cfg)
    assert whole.index.exact == (path_kind == "exact")
    assert all(e.index.exact == (path_kind == "exact") or e.num_embedded < 100 for e in sharded.engines)
    inst = InstanceConfig(min_points=3)
    for name in QUERY_SETS:
        q = sets[name]
        for top_k, thr, with_neg, with_inst in [
            (1, 0.0, True, False),
            (10, 0.0, False, True),
            (100, 0.0, True, True),
            (M, 0.0, False, False),
            (300, 0.51, True, False),
        ]:
            neg = negs if with_neg else None
            ic = inst if with_inst else None
            ref = whole.text_query_many(q, top_k, thr, None, ic, negatives=neg)
            got = sharded.text_query_many(q, top_k, thr, None, ic, negatives=neg, columns=COLUMNS)
            for a, b in zip(got, ref, strict=True):
                _same_answer(a, b)
                want = whole.gaussian_columns(b.index, COLUMNS)
                assert all(np.array_equal(a.columns[c], want[c]) for c in COLUMNS)
    # custom canonical phrases go through the exact dots of both
    canon = safe_normalize(torch.randn(3, D, generator=torch.Generator().manual_seed(9)))
    ref = whole.text_query_many(sets["clip"], 50, 0.0, canon)
    got = sharded.text_query_many(sets["clip"], 50, 0.0, canon)
    for a, b in zip(got, ref, strict=True):
        _same_answer(a, b)
