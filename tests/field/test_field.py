"""Hash encoding, bounds, field heads, selection, blending weights, relevancy."""

from __future__ import annotations

import math

import pytest
import torch

from fmgs.field.bounds import SceneBounds
from fmgs.field.hashgrid import HashGrid, HashGridConfig, corners
from fmgs.field.model import FeatureField, FieldConfig
from fmgs.field.select import SelectConfig, select_gaussians
from fmgs.gaussians import GaussianSet
from fmgs.query.relevancy import relevancy, relevancy_reference
from fmgs.render import rasterize
from fmgs.render.weights import view_weights
from tests.helpers.scenes import random_scene
from tests.helpers.tolerances import assert_close

SMALL = HashGridConfig(levels=4, min_res=2, max_res=24, log2_table=8, features=2)


def test_resolutions_follow_the_paper():
    cfg = HashGridConfig()
    res = cfg.resolutions()
    assert len(res) == 24 and res[0] == 16 and res[-1] == 512
    b = (512 / 16) ** (1 / 23)
    assert all(r == math.floor(16 * b**i + 1e-6) for i, r in enumerate(res))
    # Coarse levels are dense (fit the table), fine ones hashed at T = 2^20.
    sizes = cfg.level_sizes()
    assert sizes[0] == 17**3 and sizes[-1] == 1 << 20


def test_dense_levels_index_every_vertex_once():
    cfg = HashGridConfig(levels=1, min_res=3, max_res=3, log2_table=8, features=1)
    g = torch.stack(torch.meshgrid(*[torch.arange(4.0)] * 3, indexing="ij"), -1).reshape(-1, 3) / 3
    rows = corners(g.double(), cfg).rows
    # Each grid vertex is a corner with weight 1 of its own cell: rows hit all 64 vertices.
    w = corners(g.double(), cfg).weights
    hit = rows[w > 0.5]
    assert sorted(hit.tolist()) == list(range(64))


def test_trilinear_weights_sum_to_one_and_interpolate_linear_functions():
    x = torch.rand(200, 3, dtype=torch.float64)
    c = corners(x, SMALL)
    assert torch.allclose(c.weights.sum(-1), torch.ones_like(c.weights[..., 0]))
    # A table holding an affine function of the vertex position is reproduced exactly at any point.
    cfg = HashGridConfig(levels=1, min_res=5, max_res=5, log2_table=10, features=1)
    grid = HashGrid(cfg, dtype=torch.float64)
    v = torch.stack(torch.meshgrid(*[torch.arange(6.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    idx = (v[:, 0] + v[:, 1] * 6 + v[:, 2] * 36).long()
    f = lambda p: 0.3 + p @ torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)  # noqa: E731
    with torch.no_grad():
        grid.table[idx, 0] = f(v.double() / 5)
    assert_close(grid(x)[:, 0], f(x), torch.float64)


def test_fast_path_equals_reference_forward_and_backward():
    torch.manual_seed(1)
    grid = HashGrid(SMALL, dtype=torch.float64)
    with torch.no_grad():
        grid.table.normal_()
    x = torch.rand(300, 3, dtype=torch.float64, requires_grad=True)
    look = grid.lookup(x)
    a = grid.encode(look)
    b = grid.encode_reference(look)
    assert_close(a, b, torch.float64)
    g = torch.randn_like(a)
    ga = torch.autograd.grad((a * g).sum(), [grid.table, x], retain_graph=True)
    gb = torch.autograd.grad((b * g).sum(), [grid.table, x])
    for u, v in zip(ga, gb, strict=True):
        assert_close(u, v, torch.float64)


def test_gradcheck_table_and_positions():
    grid = HashGrid(SMALL, dtype=torch.float64)
    with torch.no_grad():
        grid.table.normal_()
    # Keep points away from cell faces, where the encoding is only piecewise smooth.
    x = (torch.rand(6, 3, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
    torch.autograd.gradcheck(lambda p: grid(p), (x,))
    tab = grid.table.detach().clone().requires_grad_()
    xd = x.detach()
    torch.autograd.gradcheck(
        lambda t: torch.func.functional_call(grid, {"table": t, "keys": grid.keys}, (xd,)), (tab,)
    )


def test_compact_grid_equals_full_grid_at_its_points_and_reads_zero_elsewhere():
    cfg = HashGridConfig(levels=6, min_res=4, max_res=64, log2_table=10, features=3)
    pts = torch.rand(500, 3, dtype=torch.float64)
    full = HashGrid(cfg, dtype=torch.float64)
    with torch.no_grad():
        full.table.normal_()
    compact = HashGrid.compact(cfg, pts, dtype=torch.float64)
    with torch.no_grad():
        compact.table.copy_(full.table[compact.keys])
    assert len(compact.keys) < len(full.keys)
    assert torch.equal(compact(pts), full(pts))
    # Elsewhere the compact grid uses the rows it holds and reads the rest as zero: equal to a full
    # grid whose untouched rows are zero.
    zeroed = HashGrid(cfg, dtype=torch.float64)
    with torch.no_grad():
        zeroed.table.zero_()
        zeroed.table[compact.keys] = full.table[compact.keys]
    other = torch.rand(300, 3, dtype=torch.float64)
    assert_close(compact(other), zeroed(other), torch.float64)


def test_bounds_contract_everything_into_the_unit_cube():
    b = SceneBounds((1.0, 2.0, 3.0), (2.0, 1.0, 0.5))
    inside = torch.tensor([[1.0, 2.0, 3.0], [3.0, 3.0, 3.5], [-1.0, 1.0, 2.5]], dtype=torch.float64)
    u = b.normalise(inside)
    assert_close(u[0], torch.full((3,), 0.5, dtype=torch.float64), torch.float64)
    assert_close(u[1], torch.tensor([0.75, 0.75, 0.75], dtype=torch.float64), torch.float64)
    far = torch.tensor([[1e30, -1e30, 0.0], [3e38, 3e38, -3e38], [5.0, 2.0, 3.0]], dtype=torch.float32)
    v = b.normalise(far)
    assert torch.isfinite(v).all() and (v >= 0).all() and (v <= 1).all()
    # Continuous across the box surface.
    eps = 1e-9
    edge = torch.tensor([[3.0 - eps, 2.0, 3.0], [3.0 + eps, 2.0, 3.0]], dtype=torch.float64)
    e = b.normalise(edge)
    assert (e[0] - e[1]).abs().max() < 1e-8
    with pytest.raises(ValueError):
        SceneBounds((0.0, 0.0, 0.0), (1.0, 0.0, 1.0))


def test_bounds_around_flat_points_stay_valid():
    pts = torch.zeros(10, 3)
    pts[:, 0] = torch.linspace(0, 1, 10)
    b = SceneBounds.around(pts)
    assert all(h > 0 for h in b.half)
    assert SceneBounds.around(torch.zeros(3, 3)).half == (1.0, 1.0, 1.0)


def test_field_outputs_unit_language_embeddings_and_far_points_stay_finite():
    cfg = FieldConfig(grid=SMALL, clip_dim=16, clip_hidden=32, clip_layers=2, dino_dim=8, dino_hidden=16)
    pts = torch.randn(100, 3)
    f = FeatureField.for_points(cfg, pts)
    out = f(pts)
    assert out.clip.shape == (100, 16) and out.dino.shape == (100, 8)
    assert torch.allclose(out.clip.norm(dim=-1), torch.ones(100), atol=1e-5)
    far = torch.tensor([[1e20, 0.0, 0.0], [-3e38, 3e38, 1.0]])
    o2 = f(far)
    assert torch.isfinite(o2.clip).all() and torch.isfinite(o2.dino).all()
    # Deterministic construction from the seed.
    g = FeatureField.for_points(cfg, pts)
    assert torch.equal(g(pts).clip, out.clip)


def test_selection_applies_opacity_and_radius():
    n = 4
    means = torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.3, 0.0], [0.0, 0.0, 0.3]])
    log_scales = torch.log(torch.tensor([[0.1] * 3, [0.1] * 3, [1e-4] * 3, [0.1] * 3]))
    opac = torch.tensor([0.9, 0.1, 0.9, 0.9])
    gs = GaussianSet(
        means, torch.tensor([[1.0, 0, 0, 0]] * n), log_scales, torch.logit(opac), torch.zeros(n, 1, 3)
    )
    from fmgs.cameras import Camera
    from tests.helpers.scenes import look_at

    cam = Camera(
        Camera.intrinsics(50, 50, 32, 24), look_at(torch.tensor([0.0, 0.0, -4.0]), torch.zeros(3)), 64, 48
    )
    sel = select_gaussians(gs, [cam], SelectConfig(rule="paper", opacity_min=0.25, radius_min=2.0))
    # 1 is too transparent, 2 is sub-pixel.
    assert sel.index.tolist() == [0, 3] and sel.total == 4 and sel.fraction == 0.5


@pytest.mark.parametrize("coverage", [0.3, 0.9, 1.0])
def test_coverage_selection_equals_one_pixel_at_a_time(coverage):
    from fmgs.field.select import covering, covering_reference

    s = random_scene(5, 300, 4, 23, 17, 20.0)
    m, q, sc, o, _, cam = s.args(torch.float64)
    vw = view_weights(m, q, sc, o, cam)
    fast, ref = covering(vw, coverage), covering_reference(vw, coverage)
    assert torch.equal(fast, ref) and len(fast) > 0
    assert coverage < 1.0 or set(fast.tolist()) == set(vw.gaussians.tolist())  # all: every contributor


def test_coverage_keeps_a_thin_object_the_paper_rule_drops():
    """A sub-pixel-wide, opaque stick in front of a large backdrop: the paper's radius test drops its
    Gaussians, so its pixels would show the backdrop's feature; coverage keeps them."""
    from fmgs.cameras import Camera
    from tests.helpers.scenes import look_at

    xs = torch.linspace(-0.5, 0.5, 21)
    stick = torch.stack([xs, torch.zeros(21), torch.zeros(21)], 1)
    means = torch.cat([stick, torch.tensor([[0.0, 0.0, 1.0]])])
    log_scales = torch.log(
        torch.cat([torch.tensor([[0.03, 0.004, 0.004]]).repeat(21, 1), torch.tensor([[2.0, 2.0, 0.01]])])
    )
    n = len(means)
    opac = torch.full((n,), 0.95)
    gs = GaussianSet(
        means, torch.tensor([[1.0, 0, 0, 0]] * n), log_scales, torch.logit(opac), torch.zeros(n, 1, 3)
    )
    cam = Camera(
        Camera.intrinsics(50, 50, 32, 24), look_at(torch.tensor([0.0, 0.0, -4.0]), torch.zeros(3)), 64, 48
    )
    paper = select_gaussians(gs, [cam], SelectConfig(rule="paper"))
    cover = select_gaussians(gs, [cam], SelectConfig())
    assert paper.index.tolist() == [21]  # only the backdrop
    assert set(range(21)) <= set(cover.index.tolist()) and 21 in cover.index.tolist()
    with pytest.raises(ValueError, match="rule"):
        SelectConfig(rule="all")
    with pytest.raises(ValueError, match="coverage"):
        SelectConfig(coverage=0.0)


@pytest.mark.parametrize("rule", ["coverage", "paper"])
def test_max_selected_keeps_the_heaviest_by_dense_per_view_sums(rule):
    """The cap keeps, of the rule's choice, the K Gaussians whose blending weight summed over every pixel
    of every view is largest; the sums here come from each view's dense weight matrix."""
    from fmgs.cameras import Camera

    scenes = [random_scene(seed, 300, 1, 29, 21, 25.0) for seed in (11, 12, 13)]
    m, q, sc, o, _, _ = scenes[0].args(torch.float32)
    gs = GaussianSet(m, q, torch.log(sc), torch.logit(o.clamp(1e-4, 1 - 1e-4)), torch.zeros(len(m), 1, 3))
    cams: list[Camera] = [s.camera for s in scenes]
    dense = torch.zeros(gs.num, dtype=torch.float64)
    for cam in cams:
        vw = view_weights(gs.means, gs.quats, gs.scales, gs.opacities, cam)
        dense[vw.gaussians] += vw.matrix.dense().double().sum(0)
    free = select_gaussians(gs, cams, SelectConfig(rule=rule))
    k = len(free.index) // 3
    w = dense[free.index]
    order = torch.argsort(-w)
    assert w[order[k - 1]] - w[order[k]] > 1e-6  # a clear cut, so rounding cannot decide it
    want = torch.sort(free.index[order[:k]]).values
    capped = select_gaussians(gs, cams, SelectConfig(rule=rule, max_selected=k))
    assert torch.equal(capped.index, want) and capped.total == gs.num
    # A cap at or above the rule's count changes nothing.
    same = select_gaussians(gs, cams, SelectConfig(rule=rule, max_selected=len(free.index)))
    assert torch.equal(same.index, free.index)
    with pytest.raises(ValueError, match="max_selected"):
        SelectConfig(max_selected=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_view_weights_render_equals_the_rasteriser(dtype):
    s = random_scene(3, 200, 6, 37, 29, 35.0)
    m, q, sc, o, f, cam = s.args(dtype)
    ref = rasterize(m, q, sc, o, f.clone().requires_grad_(), cam, backend="reference")
    vw = view_weights(m, q, sc, o, cam, dtype=dtype)
    assert ref.n_contrib is not None
    assert set(vw.gaussians.tolist()) == set(torch.nonzero(ref.n_contrib > 0).squeeze(1).tolist())
    fl = f[vw.gaussians].clone().requires_grad_()
    img = vw.render(fl)
    assert_close(img, ref.image, dtype)
    # Gradient: W^T g equals the rasteriser's feature gradient.
    g = torch.randn_like(img)
    (gl,) = torch.autograd.grad((img * g).sum(), fl)
    fr = f.clone().requires_grad_()
    out = rasterize(m, q, sc, o, fr, cam, backend="reference")
    (gr,) = torch.autograd.grad((out.image * g).sum(), fr)
    assert_close(gl, gr[vw.gaussians], dtype)


def test_relevancy_is_stable_for_huge_logits_and_matches_the_literal_form():
    q = torch.tensor([0.0, 1.0, -1.0, 500.0, -500.0, 0.3], dtype=torch.float64)
    c = torch.tensor(
        [[0.1, 0.2], [0.9, 1.2], [-1.0, 2.0], [-500.0, 499.0], [500.0, 0.0], [0.3, 0.3]], dtype=torch.float64
    )
    r = relevancy(q, c)
    assert torch.isfinite(r).all() and (r >= 0).all() and (r <= 1).all()
    assert_close(r, relevancy_reference(q, c), torch.float64)
    assert r[5] == 0.5
    r32 = relevancy(q.float() * 1e6, c.float() * 1e6)
    assert torch.isfinite(r32).all()


def test_interpolation_matrix_equals_the_gather_encoding_and_its_gradient():
    cfg = HashGridConfig(levels=5, min_res=3, max_res=40, log2_table=9, features=3)
    pts = torch.rand(120, 3, dtype=torch.float64)
    grid = HashGrid.compact(cfg, pts, dtype=torch.float64)
    with torch.no_grad():
        grid.table.normal_()
    look = grid.lookup(pts)
    a = grid.interpolation_matrix(look)
    fast, ref = grid.encode_matrix(a), grid.encode_reference(look)
    assert_close(fast, ref, torch.float64)
    g = torch.randn_like(fast)
    (ga,) = torch.autograd.grad((fast * g).sum(), grid.table)
    (gb,) = torch.autograd.grad((ref * g).sum(), grid.table)
    assert_close(ga, gb, torch.float64)


def test_scene_max_res_follows_the_point_spacing():
    from fmgs.field.hashgrid import scene_max_res

    g = torch.stack(torch.meshgrid(*[torch.arange(11.0)] * 3, indexing="ij"), -1).reshape(-1, 3) / 40
    cfg = HashGridConfig()
    assert scene_max_res(g, cfg) == 40  # spacing 1/40
    assert scene_max_res(g / 100, cfg) == cfg.max_res  # finer than the cap
    assert scene_max_res(g * 10, cfg) == cfg.min_res  # coarser than the coarsest level
    assert scene_max_res(torch.zeros(5, 3), cfg) == cfg.max_res  # coincident points
