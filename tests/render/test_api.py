"""The rasteriser interface: backend choice, lazy loading, clear errors."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from fmgs.errors import BackendUnavailableError, ValidationError
from fmgs.render import rasterize
from tests.helpers.scenes import random_scene


def _run(code: str) -> str:
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.strip()


def test_importing_the_library_loads_no_kernel():
    out = _run(
        "import sys, fmgs, fmgs.render, fmgs.io.ply, fmgs.sh;"
        "print(sorted(m for m in ('numba', 'gsplat', 'fmgs.render.cpu_kernels', 'plyfile', 'safetensors')"
        " if m in sys.modules))"
    )
    assert out == "[]"


def test_client_package_imports_without_torch():
    out = _run(
        "import sys; sys.modules['torch'] = None\n"  # any torch import now raises ImportError
        "import fmgs_client; print('ok', 'torch' in sys.modules and sys.modules['torch'] is not None)"
    )
    assert out == "ok False"


def test_auto_backend_choice():
    sc = random_scene(seed=0, n=10, d=3, width=8, height=8, focal=10.0)
    a = rasterize(*sc.args(), backend="auto")  # no grad -> cpu kernel
    b = rasterize(*sc.args(), backend="reference")
    assert torch.allclose(a.image, b.image, atol=1e-6)
    m = sc.means.float().clone().requires_grad_(True)
    out = rasterize(m, *sc.args()[1:], backend="auto")  # grad, 3 channels -> cpu with gradients
    out.image.sum().backward()
    assert m.grad is not None
    assert out.image.grad_fn is not None


def test_cpu_backend_gives_gradients():
    sc = random_scene(seed=0, n=4, d=3, width=8, height=8, focal=10.0)
    f = sc.features.float().clone().requires_grad_(True)
    m, q, s, o, _, cam = sc.args()
    rasterize(m, q, s, o, f, cam, backend="cpu").image.sum().backward()
    assert f.grad is not None and bool(f.grad.abs().sum() > 0)
    with torch.no_grad():
        rasterize(m, q, s, o, f, cam, backend="cpu")


def test_unknown_backend_and_bad_shapes():
    sc = random_scene(seed=0, n=4, d=3, width=8, height=8, focal=10.0)
    with pytest.raises(ValidationError, match="unknown backend"):
        rasterize(*sc.args(), backend="vulkan")
    m, q, s, o, f, cam = sc.args()
    with pytest.raises(ValidationError, match=r"^features: expected shape \[4,\*\]"):
        rasterize(m, q, s, o, f[:3], cam)
    with pytest.raises(ValidationError, match=r"^scales at index 0: must be positive"):
        rasterize(m, q, -s, o, f, cam)
    with pytest.raises(ValidationError, match=r"^opacities at index 0: must lie in \[0, 1\]"):
        rasterize(m, q, s, o + 2, f, cam)
    with pytest.raises(ValidationError, match=r"^background: expected shape \[3\]"):
        rasterize(m, q, s, o, f, cam, background=torch.zeros(4))


def test_empty_scene():
    sc = random_scene(seed=0, n=1, d=3, width=8, height=8, focal=10.0)
    m, q, s, o, f, cam = sc.args()
    for backend in ("reference", "cpu"):
        out = rasterize(m[:0], q[:0], s[:0], o[:0], f[:0], cam, background=torch.ones(3), backend=backend)
        assert torch.equal(out.image, torch.ones(8, 8, 3)) and (out.alpha == 0).all()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message shown when CUDA is absent")
def test_cuda_backend_without_cuda_says_why():
    sc = random_scene(seed=0, n=4, d=3, width=8, height=8, focal=10.0)
    with pytest.raises(BackendUnavailableError, match="CUDA device"):
        rasterize(*sc.args(), backend="cuda")


def test_half_precision_features():
    sc = random_scene(seed=2, n=20, d=4, width=12, height=10, focal=15.0)
    m, q, s, o, f, cam = sc.args()
    ref = rasterize(m, q, s, o, f.double(), cam, backend="cpu").image
    for dt in (torch.float16, torch.bfloat16):
        out = rasterize(m, q, s, o, f.to(dt), cam, backend="cpu")
        assert out.image.dtype == dt
        assert torch.allclose(
            out.image.double(), ref, atol=0.02 * float(ref.abs().max())
        )  # bf16 keeps 8 bits: 0.4% steps


@pytest.mark.parametrize(
    "kw",
    [
        {"eps2d": float("nan")},
        {"eps2d": -1.0},
        {"eps2d": float("inf")},
        {"fov_clip": float("nan")},
        {"fov_clip": -0.1},
    ],
)
def test_raster_config_refuses_nan_and_negative_settings(kw):
    from fmgs.render import RasterConfig

    with pytest.raises(ValueError):
        RasterConfig(**kw)


def test_exp_neg_table_is_exp_for_slightly_positive_arguments_too():
    import math

    import numpy as np

    from fmgs.render.cpu_kernels import exp_neg_table, exp_table

    table = exp_table(1.0 / 255.0)
    for x in (-5.0, -0.7, -1e-3, 0.0, 1e-9, 0.004, 0.01, 0.5):
        assert exp_neg_table(x, table) == pytest.approx(math.exp(x), rel=1e-14), x
    assert np.isfinite(table).all()


@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_between_tiles_hook_leaves_the_image_unchanged_and_can_stop_it(backend):
    sc = random_scene(seed=3, n=200, d=5, width=70, height=50, focal=60.0, background=True)
    plain = rasterize(*sc.args(), backend=backend)
    calls = []
    hooked = rasterize(*sc.args(), backend=backend, between_tiles=lambda: calls.append(1))
    assert torch.equal(plain.image, hooked.image) and torch.equal(plain.alpha, hooked.alpha)
    assert torch.equal(plain.n_contrib, hooked.n_contrib) and torch.equal(plain.weight_sum, hooked.weight_sum)
    # cpu: after projection, depth sorting and binning, then after each of the 8 batches of tiles
    assert len(calls) == (3 + 8 if backend == "cpu" else 1)

    def stop():
        raise TimeoutError("deadline")

    with pytest.raises(TimeoutError):
        rasterize(*sc.args(), backend=backend, between_tiles=stop)


def test_many_small_batches_leave_the_cpu_image_unchanged(monkeypatch):
    import fmgs.render.cpu_fast as cf

    sc = random_scene(seed=5, n=400, d=4, width=90, height=70, focal=70.0, background=True)
    plain = rasterize(*sc.args(), backend="cpu")
    monkeypatch.setattr(cf, "BATCH_PAIRS", 50)  # cut by pairs into many batches
    calls = []
    hooked = rasterize(*sc.args(), backend="cpu", between_tiles=lambda: calls.append(1))
    assert len(calls) > 3 + cf.TILE_BATCHES
    for name in ("image", "alpha", "depth", "n_contrib", "weight_sum"):
        assert torch.equal(getattr(plain, name), getattr(hooked, name)), name
