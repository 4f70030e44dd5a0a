"""CUDA paths against their CPU twins: gsplat gradients, the query engine, 3DGS and field training.

Runs only where a CUDA device and gsplat exist (benchmarks/gpu.py runs it on the device machine).
"""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch

from benchmarks.query_sets import query_sets
from fmgs.data.dataset import load_dataset
from fmgs.query.engine import EngineConfig, SceneEngine
from fmgs.query.index import IndexConfig
from fmgs.query.pose import render_pose
from fmgs.query.reference import rank_reference
from fmgs.render import rasterize
from fmgs.train.evaluate import evaluate
from fmgs.train.field import train_field
from fmgs.train.gaussians import GSTrainConfig, train_gaussians
from tests.helpers.pose_scenes import SETS, cube_camera, dot_then_render_reference, fieldlike_package
from tests.helpers.query_scenes import blob_scene, camera
from tests.helpers.scenes import random_scene
from tests.train.test_field import _cache, _cfg, _dataset, _scene
from tests.train.test_gaussians import _init_only

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
gsplat = pytest.mark.skipif(importlib.util.find_spec("gsplat") is None, reason="gsplat is not installed")
pytestmark = [pytest.mark.cuda, cuda]


def _rel_l2(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.detach().double().cpu(), b.detach().double().cpu()
    return float((a - b).norm() / b.norm().clamp_min(1e-300))


@gsplat
@pytest.mark.parametrize("d", [3, 5, 896])
def test_gsplat_gradients_match_the_reference(d):
    # Opacities below 0.99 (gsplat's alpha clamp differs above); float64 reference on the same device.
    sc = random_scene(seed=d, n=300, d=d, width=64, height=48, focal=60.0)
    sc = sc._replace(opacities=sc.opacities * 0.9)
    cot = torch.randn(48, 64, d, dtype=torch.float64, generator=torch.Generator().manual_seed(1)).cuda()
    grads = {}
    for backend, dt in (("cuda", torch.float32), ("reference", torch.float64)):
        ins = [t.to("cuda", dt).requires_grad_(True) for t in sc.args()[:5]]
        out = rasterize(*ins, sc.camera, backend=backend)
        out.means2d.retain_grad()  # as 3DGS training does: the densification statistic
        (out.image * cot.to(dt)).sum().backward()
        grads[backend] = [t.grad for t in ins] + [out.means2d.grad]
    names = ("means", "quats", "scales", "opacities", "features", "means2d")
    for name, a, b in zip(names, *grads.values(), strict=True):
        assert a is not None and torch.isfinite(a).all(), name
        # float32 fast-math geometry in gsplat against float64: features blend linearly (tight),
        # geometry goes through the conic inverse and exp (looser)
        tol = 1e-3 if name == "features" else 1e-2
        assert _rel_l2(a, b) < tol, (name, _rel_l2(a, b))


@gsplat
def test_engine_on_cuda_matches_the_cpu_engine(tmp_path):
    path, classes, _ = blob_scene(tmp_path / "blobs")
    exact = IndexConfig(rank=0)
    cpu = SceneEngine.open(path, EngineConfig(index=exact))
    gpu = SceneEngine.open(path, EngineConfig(index=exact, device="cuda"))
    assert gpu.index.device.type == "cuda" and gpu.geometry[0].is_cuda
    for q in classes:
        a, b = cpu.text_query(q, 50), gpu.text_query(q, 50)
        assert not b.index.is_cuda and not b.relevancy.is_cuda
        assert torch.equal(a.index, b.index)
        assert torch.allclose(a.relevancy, b.relevancy, atol=1e-6)
        ref = rank_reference(cpu.index.table, cpu.index.canonical, q, 50)
        assert torch.equal(cpu.selected[ref.rows], b.index)
        ra, rb = render_pose(cpu, camera(), q), render_pose(gpu, camera(), q)
        assert rb.relevancy.device.type == "cpu"
        assert float((ra.relevancy - rb.relevancy).abs().max()) < 2e-3
        assert abs(ra.argmax[0] - rb.argmax[0]) <= 1 and abs(ra.argmax[1] - rb.argmax[1]) <= 1


@gsplat
def test_gs_training_on_cuda_learns_and_densifies(data_dir, tmp_path):
    # Real photos (snowmiku), half resolution, a compressed 600-step schedule on the GPU.
    ds = load_dataset(data_dir / "snowmiku_small")
    cfg = GSTrainConfig.reduced(600, seed=0, device="cuda", image_scale=0.5)
    res = train_gaussians(ds, tmp_path / "run", cfg, progress=False)
    assert np.isfinite(res.final_loss)
    assert any(h["cloned"] + h["split"] > 0 for h in res.history)
    ev = evaluate(res.gaussians.to("cuda"), ds, scale=0.5)
    init = evaluate(_init_only(ds, cfg).to("cuda"), ds, scale=0.5)
    assert ev.psnr > init.psnr + 1.0, (init.psnr, ev.psnr)  # held-out views improve


def test_field_training_on_cuda_matches_the_cpu(tmp_path):
    ds, gs = _dataset(tmp_path), _scene()
    cache = _cache(tmp_path, ds, gs, dino=True)
    a = train_field(gs, ds, cache, tmp_path / "cpu", _cfg(steps=20), progress=False)
    b = train_field(gs, ds, cache, tmp_path / "gpu", _cfg(steps=20, device="cuda"), progress=False)
    assert torch.equal(a.selection.index, b.selection.index)
    # Same initialisation and view order; only float32 summation order differs between devices, so the
    # first loss agrees to rounding and the trajectories stay together.
    assert abs(a.losses[0] - b.losses[0]) <= 1e-5 * abs(a.losses[0]), (a.losses[0], b.losses[0])
    assert abs(a.losses[-1] - b.losses[-1]) <= 0.05 * abs(a.losses[-1]), (a.losses[-1], b.losses[-1])


@gsplat
def test_relevancy_images_agree_across_devices_at_1m(tmp_path):
    """The CPU engine (compact path: exact scores of the view's Gaussians) and the CUDA engine as it opens by
    default (exact float32 table; the triton backend where Triton is installed) give the same relevancy
    image of a 1M-Gaussian scene, each within 1e-4 of the float64 dot-then-render reference, on every query
    set. (The gsplat backend, ``backend="cuda"``, differs by more: the GPU report's agreement table.)"""
    path, emb, copies = fieldlike_package(tmp_path / "million", 1_000_000, 128, 0.004)
    cpu = SceneEngine.open(path, EngineConfig())
    gpu = SceneEngine.open(path, EngineConfig(device="cuda"))
    assert not cpu.index.exact and gpu.index.device.type == "cuda"
    sets, cam = query_sets(emb, copies, 2), cube_camera()
    worst: dict[tuple[str, str], float] = {}
    for name in SETS:
        for q in sets[name]:
            ref = dot_then_render_reference(cpu, emb, q, cam)
            a = render_pose(cpu, cam, q).relevancy.double()
            b = render_pose(gpu, cam, q).relevancy.double().cpu()
            for pair, d in (("cpu_vs_f64", a - ref), ("cuda_vs_cpu", b - a), ("cuda_vs_f64", b - ref)):
                worst[name, pair] = max(worst.get((name, pair), 0.0), float(d.abs().max()))
    assert max(worst.values()) <= 1e-4, {k: v for k, v in worst.items() if v > 1e-4}
