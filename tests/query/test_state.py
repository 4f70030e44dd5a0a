"""The compact query state saved in the package: written at export, validated and memory-mapped at load,
refused when stale, rebuilt in memory for packages without it."""

from __future__ import annotations

import logging

import pytest
import torch

import fmgs.query.index as index_mod
from benchmarks.query_sets import query_sets, scene_embeddings
from fmgs.errors import ValidationError
from fmgs.gaussians import GaussianSet
from fmgs.query.engine import EngineConfig, SceneEngine
from fmgs.query.index import IndexConfig
from fmgs.query.reference import rank_reference
from fmgs.query.state import STATE_FILE, fingerprint, load_state
from fmgs.scene.package import export_scene, load_scene
from fmgs.vecmath import safe_normalize

M, D, R = 3000, 48, 12
COMPACT = EngineConfig(index=IndexConfig(rank=R, exact_below=0))


def _package(tmp_path, name="s", rank=R, seed=2):
    g = torch.Generator().manual_seed(0)
    means = torch.rand(M, 3, generator=g)
    gs = GaussianSet.from_activated(
        means,
        torch.tensor([[1.0, 0, 0, 0]]).repeat(M, 1),
        torch.full((M, 3), 0.01),
        torch.full((M,), 0.9),
        sh=torch.zeros(M, 1, 3),
    )
    emb, copies = scene_embeddings(M, D, seed=seed, means=means)
    canon = safe_normalize(torch.randn(4, D, generator=g))
    p = export_scene(tmp_path / name, gs, torch.arange(M), emb, "test/enc", canon, query_rank=rank)
    return p, emb, emb @ canon.T, query_sets(emb, copies, 4)


def test_export_writes_the_state_and_the_server_uses_it(tmp_path, monkeypatch):
    p, emb, canon, sets = _package(tmp_path)
    assert (p / STATE_FILE).is_file()
    pkg = load_scene(p, mmap=True)
    assert pkg.query_state is not None and pkg.query_state.rank == R

    def no_build(*a, **k):
        raise AssertionError("the stored state must be used, not rebuilt")

    monkeypatch.setattr(index_mod, "build_state", no_build)
    eng = SceneEngine.open(p, COMPACT)
    assert not eng.index.exact
    for q in torch.cat(list(sets.values())):
        a = eng.index.rank(q, 25)
        ref = rank_reference(emb, canon, q, 25)
        assert torch.equal(a.rows, ref.rows)
    # The answer's rescored count reaches the engine's typed answer.
    assert eng.text_query(sets["clip"][0], 25).rescored >= 25


def test_package_without_state_still_loads(tmp_path):
    p, emb, canon, sets = _package(tmp_path, rank=0)
    assert not (p / STATE_FILE).exists()
    eng = SceneEngine.open(p, COMPACT)  # built in memory
    q = sets["clip"][1]
    assert torch.equal(eng.index.rank(q, 30).rows, rank_reference(emb, canon, q, 30).rows)


def test_other_rank_is_rebuilt_in_memory(tmp_path):
    p, emb, canon, sets = _package(tmp_path)
    eng = SceneEngine.open(p, EngineConfig(index=IndexConfig(rank=6, exact_below=0)))
    assert eng.index.state.rank == 6
    q = sets["near"][0]
    assert torch.equal(eng.index.rank(q, 30).rows, rank_reference(emb, canon, q, 30).rows)


def test_stale_or_damaged_state_is_refused(tmp_path, caplog):
    p, *_ = _package(tmp_path)
    src = fingerprint(p / "embeddings.safetensors")
    st = load_state(p / STATE_FILE, M, D, src)
    with pytest.raises(ValidationError, match="other embeddings"):
        load_state(p / STATE_FILE, M, D, "0" * 64)
    with pytest.raises(ValidationError, match=r"\[3000,48\]"):
        load_state(p / STATE_FILE, M + 1, D, src)
    # Embeddings replaced under the state: the server logs it and rebuilds the state in memory.
    other, _ = _package(tmp_path, "other", seed=3)[:2]
    (p / "embeddings.safetensors").unlink()
    (other / "embeddings.safetensors").rename(p / "embeddings.safetensors")
    with caplog.at_level(logging.WARNING):
        pkg = load_scene(p, mmap=True)
    assert pkg.query_state is None and "stale" in caplog.text
    # A state file that is not one.
    (p / STATE_FILE).write_bytes(b"not safetensors")
    with pytest.raises(ValidationError, match="cannot read"):
        load_state(p / STATE_FILE, M, D, src)
    assert st.rank == R


def test_state_version_is_checked(tmp_path):
    from safetensors.torch import load_file, save_file

    p, *_ = _package(tmp_path)
    f = p / STATE_FILE
    from safetensors import safe_open

    with safe_open(str(f), framework="pt") as h:
        meta = dict(h.metadata())
    save_file(load_file(str(f)), str(f), metadata={**meta, "version": "99"})
    with pytest.raises(ValidationError, match="version '99'"):
        load_state(f, M, D, fingerprint(p / "embeddings.safetensors"))
    bad = load_file(str(f))
    bad["res_norm"] = -bad["res_norm"].abs() - 1
    save_file(bad, str(f), metadata=meta)
    with pytest.raises(ValidationError, match="res_norm must be finite and non-negative"):
        load_state(f, M, D, fingerprint(p / "embeddings.safetensors"))


def test_second_tier_is_stored_mapped_and_checked(tmp_path):
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    p, emb, canon, sets = _package(tmp_path)
    f = p / STATE_FILE
    src = fingerprint(p / "embeddings.safetensors")
    st = load_state(f, M, D, src)
    assert st.tier2 is not None and st.tier2.mapped and R + st.tier2.rank < D
    eng = SceneEngine.open(p, COMPACT)
    assert eng.index.second_tier is not None
    # Its codes are memory-mapped: not counted as resident.
    assert eng.index.nbytes() < M * (R + 4 * 4 + 1) + 8 * D * (R + st.tier2.rank) + 4 * (R + st.tier2.rank)
    for q in sets["clip"]:
        assert torch.equal(eng.index.rank(q, 40).rows, rank_reference(emb, canon, q, 40).rows)
    with safe_open(str(f), framework="pt") as h:
        meta = dict(h.metadata())
    tensors = load_file(str(f))
    # A version-1 state (first tier only) is refused, naming its version, the one read and the fix; the
    # server then builds the state in memory (both tiers) and answers exactly.
    v1 = {k: v for k, v in tensors.items() if not k.endswith("2")}
    save_file(v1, str(f), metadata={k: v for k, v in meta.items() if "2" not in k} | {"version": "1"})
    with pytest.raises(ValidationError, match=r"version '1', this build reads version 3 only: .*fmgs build"):
        load_state(f, M, D, src)
    eng = SceneEngine.open(p, COMPACT)
    assert eng.index.second_tier is not None and not eng.index.second_tier.mapped and not eng.index.exact
    q = sets["absent"][0]
    assert torch.equal(eng.index.rank(q, 40).rows, rank_reference(emb, canon, q, 40).rows)
    # Declared but missing, or damaged.
    save_file(v1, str(f), metadata=meta)
    with pytest.raises(ValidationError, match="second tier declared"):
        load_state(f, M, D, src)
    bad = dict(tensors)
    bad["bounds2"] = bad["bounds2"].clone()
    bad["bounds2"][5, 1] = float("nan")
    save_file(bad, str(f), metadata=meta)
    with pytest.raises(ValidationError, match="bounds2 must be finite and non-negative"):
        load_state(f, M, D, src)
    bad["bounds2"] = tensors["bounds2"][:-1]
    save_file(bad, str(f), metadata=meta)
    with pytest.raises(ValidationError, match=r"bounds2 must be torch.float32 \[3000, 2\]"):
        load_state(f, M, D, src)
    # rank2 = 0 in the configuration: the stored second tier is not used.
    save_file(tensors, str(f), metadata=meta)
    eng = SceneEngine.open(p, EngineConfig(index=IndexConfig(rank=R, rank2=0, exact_below=0)))
    assert eng.index.second_tier is None


def test_split_second_tier_round_trips_and_version_2_is_refused(tmp_path):
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    from fmgs.query.state import build_state, save_state

    emb, _ = scene_embeddings(M, D, seed=3)
    src = "fingerprint"
    f = tmp_path / STATE_FILE
    st = build_state(emb.half(), R, head=3)  # ranks 12 + 3 + the rest (32: TIER2_TAIL_MIN)
    t2 = st.tier2
    assert t2.head == 3 and t2.tail is not None and t2.tail.shape[1] >= 32 and t2.rank == 3 + t2.tail.shape[1]
    # The head's norms bound what it leaves: f.v - c'.w - c2a'.w2a within e1|w| + e2a|w2a| + res2a|v_perp|.
    v = safe_normalize(torch.randn(5, D, dtype=torch.float64, generator=torch.Generator().manual_seed(1)))
    B, B2a = st.basis, t2.basis[:3]
    approx = (
        st.codes.double() * st.scales.double() @ (v @ B.T).T
        + t2.codes.double() * t2.scales[:3].double() @ (v @ B2a.T).T
    )
    perp = (v - (v @ B.T) @ B - (v @ B2a.T) @ B2a).norm(dim=1)
    width = (
        st.err_norm.double()[:, None] * (v @ B.T).norm(dim=1)
        + t2.head_bounds[:, :1].double() * (v @ B2a.T).norm(dim=1)
        + t2.head_bounds[:, 1:].double() * perp
    )
    err = (emb.half().double() @ v.T - approx).abs()
    assert bool((err <= width + 1e-12).all()) and float((width - err).median()) < 0.5
    save_state(st, f, src)
    back = load_state(f, M, D, src)
    for a, b in (
        (t2.codes, back.tier2.codes),
        (t2.tail, back.tier2.tail),
        (t2.head_bounds, back.tier2.head_bounds),
    ):
        assert torch.equal(a, b)
    assert back.tier2.head == 3 and back.tier2.mapped
    with safe_open(str(f), framework="pt") as h:
        meta = dict(h.metadata())
    tensors = load_file(str(f))
    # Declared but missing, or damaged.
    save_file({k: v for k, v in tensors.items() if k != "codes2_tail"}, str(f), metadata=meta)
    with pytest.raises(ValidationError, match="second tier declared"):
        load_state(f, M, D, src)
    bad = dict(tensors)
    bad["bounds2_head"] = bad["bounds2_head"].clone()
    bad["bounds2_head"][7, 0] = -1.0
    save_file(bad, str(f), metadata=meta)
    with pytest.raises(ValidationError, match="bounds2_head must be finite and non-negative"):
        load_state(f, M, D, src)
    save_file(tensors, str(f), metadata=meta | {"head2": str(t2.rank + 1)})
    with pytest.raises(ValidationError, match="head"):
        load_state(f, M, D, src)
    # A second tier stored whole (head2 = rank2, no tail) loads without a tail.
    whole = build_state(emb.half(), R, head=0)
    assert whole.tier2.tail is None and whole.tier2.head == whole.tier2.rank
    save_state(whole, f, src)
    back = load_state(f, M, D, src)
    assert (
        back.tier2.tail is None
        and back.tier2.head_bounds is None
        and torch.equal(back.tier2.codes, whole.tier2.codes)
    )
    # A version-2 state (the second tier stored whole, no head2) is refused with the fix.
    with safe_open(str(f), framework="pt") as h:
        meta = {k: v for k, v in dict(h.metadata()).items() if k != "head2"} | {"version": "2"}
    save_file(load_file(str(f)), str(f), metadata=meta)
    with pytest.raises(ValidationError, match=r"version '2', this build reads version 3 only: .*fmgs build"):
        load_state(f, M, D, src)
