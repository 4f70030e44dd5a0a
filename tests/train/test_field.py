"""Field distillation: losses, determinism, resume, ablations, and the scene package round trip."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from fmgs.cameras import Camera
from fmgs.data.dataset import Frame, PosedDataset
from fmgs.errors import ValidationError
from fmgs.features.cache import FeatureCache, FeatureCacheWriter, TargetInfo
from fmgs.field.hashgrid import HashGridConfig
from fmgs.field.model import FieldConfig
from fmgs.gaussians import GaussianSet
from fmgs.render import rasterize
from fmgs.train import field as field_mod
from fmgs.train.field import FieldTrainConfig, dotsim_loss, train_field
from fmgs.vecmath import safe_normalize
from tests.helpers.scenes import look_at
from tests.helpers.tolerances import assert_close

SMALL_FIELD = FieldConfig(
    grid=HashGridConfig(levels=6, min_res=4, max_res=64, log2_table=12, features=2),
    clip_hidden=32,
    clip_layers=2,
    dino_hidden=16,
)


def _scene(n: int = 300, seed: int = 0) -> GaussianSet:
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 2
    quats = torch.randn(n, 4, generator=g)
    log_scales = torch.full((n, 3), -2.3) + 0.2 * torch.randn(n, 3, generator=g)
    opac = torch.logit(torch.full((n,), 0.9))
    return GaussianSet(means, quats, log_scales, opac, torch.zeros(n, 1, 3))


def _dataset(tmp: Path, views: int = 6, w: int = 24, h: int = 18) -> PosedDataset:
    frames = []
    for v in range(views):
        a = 2 * np.pi * v / views
        eye = torch.tensor([4 * np.cos(a), 4 * np.sin(a), 1.0])
        V = look_at(eye, torch.zeros(3), up=(0.0, 0.0, -1.0))
        cam = Camera(Camera.intrinsics(20.0, 20.0, w / 2, h / 2), V, w, h)
        frames.append(Frame(f"{v:03d}.png", tmp / f"{v:03d}.png", cam))
    return PosedDataset(tmp, frames)


def _cache(
    tmp: Path, ds: PosedDataset, gs: GaussianSet, dino: bool, dc: int = 8, dd: int = 4
) -> FeatureCache:
    """Targets rendered from a known per-Gaussian 'truth' (side of the scene), so they are learnable."""
    left = (gs.means[:, 0] > 0).float()[:, None]
    basis = safe_normalize(torch.randn(2, dc, generator=torch.Generator().manual_seed(1)))
    truth = safe_normalize(left * basis[0] + (1 - left) * basis[1])
    dtruth = torch.cat([left, 1 - left, gs.means[:, :2]], 1)[:, :dd]
    targets = {"clip": TargetInfo("test/clip", dc, True)}
    if dino:
        targets["dino"] = TargetInfo("test/dino", dd, False)
    with FeatureCacheWriter(tmp / "cache", targets) as w:
        for f in ds.frames:
            cam = f.camera
            args = (gs.means, gs.quats, gs.scales, gs.opacities)
            clip = safe_normalize(rasterize(*args, truth, cam).image)
            d = rasterize(*args, dtruth, cam).image if dino else None
            mask = rasterize(*args, torch.ones(gs.num, 1), cam).alpha > 0.5
            clip = torch.where(mask[..., None], clip, torch.zeros_like(clip))
            w.add(f.name, clip=clip, dino=d, mask=mask)
    return FeatureCache.open(tmp / "cache")


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("field")
    ds = _dataset(tmp)
    gs = _scene()
    return tmp, ds, gs, _cache(tmp, ds, gs, dino=True)


def _cfg(**kw) -> FieldTrainConfig:
    base = dict(
        steps=60,
        dotsim_start=30,
        lr=0.02,
        lr_final=0.015,
        field=SMALL_FIELD,
        holdout_every=0,
        checkpoint_every=0,
    )
    return FieldTrainConfig(**{**base, **kw})


def test_dotsim_matches_a_direct_double_loop():
    g = torch.Generator().manual_seed(0)
    clip, dino = torch.randn(5, 4, 6, generator=g), torch.randn(5, 4, 3, generator=g)
    f, d = safe_normalize(clip), safe_normalize(dino)
    vals = []
    for y in range(5):
        for x in range(4):
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    yy, xx = y + dy, x + dx
                    if (dy, dx) != (0, 0) and 0 <= yy < 5 and 0 <= xx < 4:
                        vals.append(abs(float(d[y, x] @ d[yy, xx]) - float(f[y, x] @ f[yy, xx])))
    assert abs(float(dotsim_loss(clip, dino, 3)) - np.mean(vals)) < 1e-6
    # Identical similarity structure costs nothing; the DINO side gets no gradient.
    assert float(dotsim_loss(dino, dino, 3)) < 1e-6
    dd = dino.clone().requires_grad_()
    cc = clip.clone().requires_grad_()
    dotsim_loss(cc, dd, 3).backward()
    assert dd.grad is None and cc.grad is not None and torch.isfinite(cc.grad).all()


def test_training_lowers_the_loss_and_is_deterministic(setup, tmp_path):
    _, ds, gs, cache = setup
    a = train_field(gs, ds, cache, tmp_path / "a", _cfg(), progress=False)
    b = train_field(gs, ds, cache, tmp_path / "b", _cfg(), progress=False)
    assert a.losses == b.losses
    assert np.mean(a.losses[-10:]) < 0.8 * np.mean(a.losses[:10])
    assert all(np.isfinite(a.losses))
    sa, sb = a.model.state_dict(), b.model.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    meta = json.loads((tmp_path / "a" / "field_train.json").read_text())
    assert meta["selected"] == len(a.selection.index) and meta["steps"] == 60
    field = meta["config"]["field"]  # the dims that ran, from the cache (not the config's 512/384)
    assert field["clip_dim"] == cache.targets["clip"].dim
    assert field["dino_dim"] == (cache.targets["dino"].dim if "dino" in cache.targets else 0)


def test_resume_after_interruption_gives_the_same_model(setup, tmp_path, monkeypatch):
    _, ds, gs, cache = setup
    cfg = _cfg(steps=30, dotsim_start=15, checkpoint_every=10)
    ref = train_field(gs, ds, cache, tmp_path / "ref", cfg, progress=False)
    calls = {"n": 0}
    real = field_mod.view_loss

    def flaky(*a, **k):
        calls["n"] += 1
        if calls["n"] == 25:  # past the checkpoint at step 20
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(field_mod, "view_loss", flaky)
    with pytest.raises(KeyboardInterrupt):
        train_field(gs, ds, cache, tmp_path / "run", cfg, progress=False)
    monkeypatch.setattr(field_mod, "view_loss", real)
    res = train_field(gs, ds, cache, tmp_path / "run", cfg, progress=False)
    assert res.losses == ref.losses
    sa, sb = res.model.state_dict(), ref.model.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    # A checkpoint written with other settings is refused, not silently mixed.
    with pytest.raises(ValidationError, match="other settings"):
        other = _cfg(steps=30, dotsim_start=15, checkpoint_every=10, lr=1e-3)
        train_field(gs, ds, cache, tmp_path / "run", other, progress=False)


@pytest.mark.parametrize("variant", ["no-dino", "per-gaussian", "no-dotsim"])
def test_ablations_train(setup, tmp_path, variant):
    tmp, ds, gs, cache = setup
    kw = {"per-gaussian": {"per_gaussian": True}, "no-dotsim": {"dotsim_weight": 0.0}}.get(variant, {})
    if variant == "no-dino":
        cache = _cache(tmp / "nodino", ds, gs, dino=False)
    res = train_field(gs, ds, cache, tmp_path, _cfg(**kw), progress=False)
    assert np.mean(res.losses[-10:]) < np.mean(res.losses[:10])


def test_missing_targets_are_named(setup, tmp_path):
    tmp, ds, gs, cache = setup
    extra = Frame("zzz.png", tmp / "zzz.png", ds.frames[0].camera)
    ds2 = PosedDataset(ds.root, [*ds.frames, extra])
    with pytest.raises(ValidationError, match=r"zzz\.png"):
        train_field(gs, ds2, cache, tmp_path, _cfg(), progress=False)


def test_package_round_trip_and_queries(setup, tmp_path):
    from fmgs.build import package_from_field
    from fmgs.query.engine import EngineConfig, SceneEngine
    from fmgs.query.pose import render_pose
    from fmgs.query.relevancy import TEMPERATURE, relevancy
    from fmgs.render import rasterize
    from fmgs.scene.package import load_scene

    _, ds, gs, cache = setup
    res = train_field(gs, ds, cache, tmp_path / "t", _cfg(), progress=False)

    class Enc:
        id, dim = "test/clip", 8
        basis = safe_normalize(torch.randn(6, 8, generator=torch.Generator().manual_seed(5)))

        def encode_text(self, texts):
            return self.basis[: len(texts)]

    enc = Enc()
    pkg = package_from_field(tmp_path / "models" / "toy", gs, res, enc)
    scene = load_scene(pkg)
    assert scene.encoder_id == "test/clip" and scene.dim == 8
    assert scene.embeddings.shape == (len(res.selection.index), 8)
    assert torch.equal(scene.selected, res.selection.index)
    # No DINO head unless asked for; no optimiser state.
    from safetensors import safe_open

    with safe_open(str(pkg / "field.safetensors"), framework="pt") as f:
        keys = list(f.keys())
    assert not any(k.startswith("dino_head") for k in keys)
    # The default stored embeddings (K=8, the manifest says so): the neighbour mean of the field decoded
    # at the means over dense neighbourhoods (to float16 rounding); K=1, the paper's rule, the field.
    from fmgs.build.config import EMBEDDING_NEIGHBOURS
    from fmgs.field.neighbours import neighbour_mean_reference, reach_of

    assert scene.manifest.extra["embedding_neighbours"] == EMBEDDING_NEIGHBOURS == 8
    g = gs.subset(scene.selected)
    with torch.no_grad():
        dec = scene.field(g.means).clip
    ref = neighbour_mean_reference(g.means, reach_of(g.scales), dec, 8)
    assert (ref - scene.embeddings).abs().max() < 1e-3  # float16 rounds values below 1 by <= 4.9e-4
    assert (dec - scene.embeddings).abs().max() > 2e-3  # the mean did change some (the toy field is smooth)
    paper = load_scene(package_from_field(tmp_path / "models" / "k1", gs, res, enc, neighbours=1))
    assert paper.manifest.extra["embedding_neighbours"] == 1
    assert (dec - paper.embeddings).abs().max() < 2e-3
    with pytest.raises(ValidationError, match="neighbours"):
        package_from_field(tmp_path / "models" / "bad", gs, res, enc, neighbours=0)
    assert not (tmp_path / "models" / "bad").exists()
    # Text query through the served engine: ranking is by relevancy, descending, indices into all Gaussians.
    engine = SceneEngine(scene, EngineConfig(backend="reference"))
    q = safe_normalize(torch.randn(8))
    r = engine.text_query(q, top_k=25)
    assert len(r.index) == 25 and bool((r.relevancy[:-1] >= r.relevancy[1:]).all())
    assert set(r.index.tolist()) <= set(scene.selected.tolist())
    # Dot-then-render (with the canonical dots stored at export) equals render-then-dot with the
    # encoder's canonical embeddings.
    cam = ds.frames[1].camera
    fast = render_pose(engine, cam, q, ("relevancy", "alpha"))
    out = rasterize(*engine.geometry, scene.embeddings, cam, backend="reference")
    canon = enc.encode_text(["object", "stuff", "things", "texture"])
    ref = relevancy(out.image @ q, out.image @ canon.T, TEMPERATURE)
    assert_close(fast.relevancy, ref, torch.float32)
    assert torch.isfinite(fast.relevancy).all() and torch.equal(fast.alpha, out.alpha)


def test_target_scales_are_the_masked_mean_squares(setup):
    _, ds, gs, cache = setup
    views = field_mod.prepare_views(gs, ds, cache, list(range(len(ds.frames))), torch.device("cpu"))
    assert field_mod.target_scales(views, "paper") == (1.0, 1.0)
    clip_ms, dino_ms = field_mod.target_scales(views, "scale")
    # The twin: a loop over every masked pixel of every view.
    sums, counts = [0.0, 0.0], [0, 0]
    for v in views:
        for i in range(v.clip.shape[0]):
            if v.mask is not None and not bool(v.mask[i]):
                continue
            for k, t in enumerate((v.clip[i], v.dino[i])):
                sums[k] += float((t.double() ** 2).sum())
                counts[k] += t.numel()
    assert clip_ms == pytest.approx(sums[0] / counts[0], rel=1e-5)
    assert dino_ms == pytest.approx(sums[1] / counts[1], rel=1e-5)
    # The test cache's targets differ in scale: unit-norm language, DINO of a larger magnitude.
    assert dino_ms > 2 * clip_ms


def test_scale_balance_divides_each_term_by_its_targets_scale(setup, tmp_path):
    _, ds, gs, cache = setup
    short = train_field(gs, ds, cache, tmp_path / "m", _cfg(steps=5), progress=False)
    g, model = gs.subset(short.selection.index), short.model
    views = field_mod.prepare_views(g, ds, cache, [0], torch.device("cpu"))
    interp = model.grid.interpolation_matrix(model.lookup(g.means))
    cfg = _cfg(balance="scale")
    with torch.no_grad():
        _, raw = field_mod.view_loss(model, interp, views[0], cfg, dotsim=False)
        _, scaled = field_mod.view_loss(model, interp, views[0], cfg, False, (0.5, 4.0))
    assert scaled["clip"] == pytest.approx(raw["clip"] / 0.5, rel=1e-6)
    assert scaled["dino"] == pytest.approx(raw["dino"] / 4.0, rel=1e-6)
    res = train_field(gs, ds, cache, tmp_path / "s", _cfg(balance="scale"), progress=False)
    assert all(np.isfinite(res.losses)) and np.mean(res.losses[-10:]) < np.mean(res.losses[:10])
    with pytest.raises(ValueError, match="balance"):
        _cfg(balance="equal")


def test_a_view_with_no_supervised_pixel_adds_no_target_loss(setup, tmp_path):
    """A view whose mask keeps no pixel (label targets of a view that shows only background) adds nothing to
    the language and DINO terms: zero, not the NaN of a mean over no element."""
    _, ds, gs, cache = setup
    short = train_field(gs, ds, cache, tmp_path / "m", _cfg(steps=2), progress=False)
    g, model = gs.subset(short.selection.index), short.model
    view = field_mod.prepare_views(g, ds, cache, [0], torch.device("cpu"))[0]
    empty = view._replace(mask=torch.zeros_like(view.mask))
    interp = model.grid.interpolation_matrix(model.lookup(g.means))
    for dotsim in (False, True):
        model.zero_grad()
        loss, parts = field_mod.view_loss(model, interp, empty, _cfg(), dotsim)
        loss.backward()
        assert parts["clip"] == 0 and parts["dino"] == 0
        assert float(loss.detach()) == pytest.approx(_dotsim_part(parts, dotsim), rel=1e-6)
        assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
    with pytest.raises(ValidationError, match="not all zero"):  # no scale to divide by: refused, not 1e12
        field_mod.target_scales([empty], "scale")
    zero = view._replace(dino=torch.zeros_like(view.dino))
    with pytest.raises(ValidationError, match="DINO targets"):
        field_mod.target_scales([zero], "scale")
    assert all(s > 0 for s in field_mod.target_scales([empty, view], "scale"))  # one empty view is fine


def _dotsim_part(parts: dict, dotsim: bool) -> float:
    """The loss left when the target terms are zero: the weighted dotsim term, if on."""
    return _cfg().dotsim_weight * parts["dotsim"] if dotsim else 0.0
