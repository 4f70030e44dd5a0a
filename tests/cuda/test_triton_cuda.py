"""The triton backend's compiled kernels on a CUDA device against the float64 reference.

tests/render/test_triton_blend.py checks the same kernels' logic in Triton's interpreter on the CPU; here
the compiled code (fused multiply-adds, tensor-core products, pipelined loops) is held to the same
bounds, on the paper's 899-channel garden render (the 1M-Gaussian relevancy images: test_cuda_paths.py).
"""

from __future__ import annotations

import importlib.util

import pytest
import torch

from benchmarks.common import fieldlike
from benchmarks.scenes import garden
from fmgs.render import rasterize
from tests.helpers.scenes import random_scene
from tests.helpers.tolerances import assert_close, rel_err
from tests.render.test_stiff import stacked_layers

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
has_triton = pytest.mark.skipif(importlib.util.find_spec("triton") is None, reason="Triton is not installed")
pytestmark = [pytest.mark.cuda, cuda, has_triton]

SWEEP = {}
if importlib.util.find_spec("triton") is not None:
    from fmgs.render.triton_blend import SWEEP  # the launches benchmarks/gpu_parts.py times


@pytest.mark.parametrize("name", SWEEP)
def test_every_launch_matches_the_float64_reference(name):
    from fmgs.render.triton_blend import rasterize_triton

    # 200 channels: at least three blocks of every launch's width, so the weights-once path runs where set
    sc = random_scene(seed=7, n=400, d=200, width=83, height=61, focal=60.0, background=True)
    dev = [t.cuda() for t in sc.args()[:5]]
    out = rasterize_triton(*dev, sc.camera, sc.background.float().cuda(), tuning=SWEEP[name])
    ref = rasterize(*sc.args(torch.float64), background=sc.background, backend="reference")
    for what in ("image", "alpha", "depth"):
        assert_close(getattr(out, what), getattr(ref, what), torch.float32, f"{name} {what}")


@pytest.mark.parametrize("opacity", [1 - 1e-7, 0.02])
def test_stacked_layers_terminate_as_the_reference(opacity):
    sc = stacked_layers(opacity)
    ref = rasterize(*sc.args(torch.float64), backend="reference")
    out = rasterize(*[t.cuda() for t in sc.args()[:5]], sc.camera, backend="triton")
    assert_close(out.image, ref.image, torch.float32, "image")
    assert_close(out.alpha, ref.alpha, torch.float32, "alpha")


def test_paper_render_within_1e4_of_float64():
    """CLIP 512 + DINO 384 + RGB of the garden at 480x270 (benchmarks/gpu_parts.py part "paper")."""
    s = garden()
    cam = s.cameras[0].resized(480, 270)
    feats = torch.cat([fieldlike(s.means, 512, seed=1), fieldlike(s.means, 384, seed=2) * 3, s.colors], 1)
    geo = (s.means, s.quats, s.scales, s.opacities)
    out = rasterize(*[t.cuda() for t in geo], feats.cuda(), cam, backend="triton")
    ref = rasterize(*[t.cuda().double() for t in geo], feats.cuda().double(), cam, backend="reference")
    assert rel_err(out.image, ref.image) <= 1e-4
    assert rel_err(out.alpha, ref.alpha) <= 1e-5


def test_projection_kernel_matches_project_on_the_gpu():
    from fmgs.render.projection import project
    from fmgs.render.triton_blend import project_triton
    from fmgs.render.types import RasterConfig

    s = garden()
    cam = s.cameras[0].resized(480, 270)
    geo = [t.cuda() for t in (s.means, s.quats, s.scales, s.opacities)]
    a = project(*geo, cam, RasterConfig())
    b = project_triton(*geo, cam, RasterConfig())
    assert torch.equal(a.visible, b.visible) and torch.equal(a.bbox, b.bbox) and torch.equal(a.radii, b.radii)
    for name in ("means2d", "depths", "conics"):
        x, y = getattr(a, name)[a.visible], getattr(b, name)[a.visible]
        assert float(((x - y).abs() / x.abs().clamp_min(1e-300)).max()) <= 1e-12, name
