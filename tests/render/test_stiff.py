"""Stiff and extreme inputs (docs/rendering.md#the-rendering-rule-every-backend): finite outputs everywhere,
float64 agreement where defined."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
import torch

from fmgs.cameras import Camera, quat_wxyz_to_rotmat
from fmgs.errors import ValidationError
from fmgs.render import RasterConfig, rasterize
from tests.helpers.brute_force import brute_force_render
from tests.helpers.scenes import RandomScene, look_at, random_scene
from tests.helpers.tolerances import assert_close

BACKENDS = ["reference", "cpu"]


def _all_finite(out) -> None:
    for name in ("image", "alpha", "depth", "means2d", "weight_sum"):
        t = getattr(out, name)
        assert torch.isfinite(t).all(), f"non-finite {name}"
    assert (out.radii >= 0).all()


def _check_all(sc: RandomScene, dtype=torch.float32, backends=BACKENDS, grads: bool = False):
    ref = brute_force_render(**sc.brute_args(dtype))
    assert np.isfinite(ref.image).all()
    outs = {}
    for backend in backends:
        bg = None if sc.background is None else sc.background.to(dtype)
        out = rasterize(*sc.args(dtype), background=bg, backend=backend)
        _all_finite(out)
        assert_close(out.image, ref.image, dtype, f"{backend} image")
        assert_close(out.alpha, ref.alpha, dtype, f"{backend} alpha")
        assert_close(out.depth, ref.depth, dtype, f"{backend} depth")
        np.testing.assert_array_equal(out.n_contrib.numpy(), ref.n_contrib)
        outs[backend] = out
    if grads:
        leaves = [
            t.to(dtype).clone().requires_grad_(True) for t in (sc.means, sc.quats, sc.scales, sc.features)
        ]
        m, q, s, f = leaves
        out = rasterize(m, q, s, sc.opacities.to(dtype), f, sc.camera, backend="reference")
        (out.image.sum() + out.depth.sum() + out.alpha.sum()).backward()
        for t in leaves:
            assert torch.isfinite(t.grad).all()
    return ref, outs


def _scene(
    means,
    quats,
    scales,
    opac,
    feats=None,
    width=24,
    height=18,
    focal=20.0,
    viewmat=None,
    near=0.01,
    background=None,
) -> RandomScene:
    t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64))  # noqa: E731
    means, quats, scales, opac = t(means), t(quats), t(scales), t(opac)
    n = means.shape[0]
    feats = (
        t(feats) if feats is not None else torch.linspace(0.5, 1.5, n * 3, dtype=torch.float64).reshape(n, 3)
    )
    K = Camera.intrinsics(focal, focal, width / 2, height / 2)
    cam = Camera(K, torch.eye(4) if viewmat is None else viewmat, width, height, near=near)
    return RandomScene(means, quats, scales, opac, feats, cam, background)


def _rand_quats(n, seed):
    return np.random.default_rng(seed).normal(size=(n, 4))


@pytest.mark.parametrize("ratio", [1e6, 1e7])
@pytest.mark.parametrize("shape", ["needle", "pancake"])
def test_extreme_anisotropy(ratio, shape):
    n = 12
    rng = np.random.default_rng(int(math.log10(ratio)))
    means = rng.normal(size=(n, 3)) * 0.4 + [0, 0, 4]
    base = (
        np.array([1.0, 1.0 / ratio, 1.0 / ratio]) if shape == "needle" else np.array([1.0, 1.0, 1.0 / ratio])
    )
    scales = 0.3 * base[None].repeat(n, 0)
    # Include axis-aligned and diagonal orientations (the worst case for a*c - b^2 cancellation).
    quats = np.concatenate(
        [[[1, 0, 0, 0], [0.924, 0, 0, 0.383], [0.854, 0.146, 0.354, 0.354]], _rand_quats(n - 3, 5)]
    )
    _check_all(_scene(means, quats, scales, np.full(n, 0.9)), grads=True)


def _exact_alpha_image(sc: RandomScene, config: RasterConfig) -> np.ndarray:
    """[H,W] alpha of a single Gaussian with the covariance, its inverse and the power in exact rationals
    (from the float64 inputs and the code's own rotation matrix); only exp() is rounded."""
    F = Fraction
    cam = sc.camera
    fx, fy, cx, cy = (F(v) for v in (cam.fx, cam.fy, cam.cx, cam.cy))
    W, H = cam.width, cam.height
    p = [F(float(v)) for v in sc.means[0]]  # identity viewmat: camera coordinates
    Rq = quat_wxyz_to_rotmat(sc.quats.to(torch.float64))[0]
    L = [[F(float(Rq[i, j])) * F(float(sc.scales[0, j])) for j in range(3)] for i in range(3)]
    clip = F(config.fov_clip)
    lim_x = (-(cx / fx + clip * W / 2 / fx), (W - cx) / fx + clip * W / 2 / fx)
    lim_y = (-(cy / fy + clip * H / 2 / fy), (H - cy) / fy + clip * H / 2 / fy)
    z = p[2]
    tx = z * min(max(p[0] / z, lim_x[0]), lim_x[1])
    ty = z * min(max(p[1] / z, lim_y[0]), lim_y[1])
    J = [[fx / z, 0, -fx * tx / z**2], [0, fy / z, -fy * ty / z**2]]
    M = [[sum(J[r][k] * L[k][c] for k in range(3)) for c in range(3)] for r in range(2)]
    eps = F(config.eps2d)
    a = sum(m * m for m in M[0]) + eps
    b = sum(m0 * m1 for m0, m1 in zip(M[0], M[1], strict=True))
    c = sum(m * m for m in M[1]) + eps
    det = a * c - b * b
    u, v = fx * p[0] / z + cx, fy * p[1] / z + cy
    o = float(sc.opacities[0])
    out = np.full((H, W), np.nan)  # NaN: within 1e-6 of alpha_min, where rounding may decide
    for i in range(H):
        for j in range(W):
            dx, dy = j + F(1, 2) - u, i + F(1, 2) - v
            power = float((c * dx * dx - 2 * b * dx * dy + a * dy * dy) / det)
            alpha = min(o * math.exp(-0.5 * power), config.alpha_max)
            if abs(alpha / config.alpha_min - 1) > 1e-6:
                out[i, j] = alpha if alpha >= config.alpha_min else 0.0
    return out


@pytest.mark.parametrize("distance", [1e4, 1e5, 1e6])
@pytest.mark.parametrize("backend", [*BACKENDS, "cpu-grad"])
def test_needle_seen_far_from_its_centre_keeps_its_precision(distance, backend):
    """A needle whose centre projects ``distance`` px off-image and which reaches into it at an angle:
    in conic form (A dx^2 + 2B dx dy + C dy^2) its terms are ~1e10 times the power at 1e5 px and alpha
    lost up to 6 digits (1e-4 relative at 1e6 px). The completed-square form leaves only the rounding of
    the projected centre, an error proportional to the distance: bounded here by 2e-15 per pixel."""
    W = H = 32
    focal, depth, theta = 1024.0, 8.0, 0.3
    u0, v0 = W / 2 - distance * math.cos(theta), H / 2 - distance * math.sin(theta)
    long_px = distance / 2.5  # alpha stays visible across the image at this distance
    sc = _scene(
        [[(u0 - W / 2) / focal * depth, (v0 - H / 2) / focal * depth, depth]],
        [[math.cos(theta / 2), 0, 0, math.sin(theta / 2)]],
        [[long_px * depth / focal, 1e-3, 1e-3]],
        [0.9],
        feats=[[1.0]],
        width=W,
        height=H,
        focal=focal,
    )
    config = RasterConfig()
    exact = _exact_alpha_image(sc, config)
    lit = exact > 0
    assert lit.sum() > 50 and (exact == 0).sum() > 500  # the needle crosses the image, with edges
    feats = sc.features.clone().requires_grad_(backend == "cpu-grad")
    with torch.set_grad_enabled(backend == "cpu-grad"):
        out = rasterize(
            sc.means, sc.quats, sc.scales, sc.opacities, feats, sc.camera, config=config,
            backend="cpu" if backend == "cpu-grad" else backend,
        ).alpha.detach().numpy()  # fmt: skip
    known = ~np.isnan(exact)
    np.testing.assert_array_equal(out[known & ~lit], 0.0)
    rel = np.abs(out[lit] - exact[lit]) / exact[lit]
    assert rel.max() <= 2e-15 * distance, f"alpha relative error {rel.max():.2e} at {distance:.0e} px"


def test_sub_pixel_gaussians():
    n = 20
    rng = np.random.default_rng(1)
    means = np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(3, 6, n)]
    _check_all(_scene(means, _rand_quats(n, 2), np.full((n, 3), 1e-5), np.full(n, 0.95)), grads=True)


def test_gaussian_covering_whole_image():
    means = [[0.0, 0.0, 4.0], [0.3, -0.2, 5.0]]
    scales = [[100.0, 80.0, 50.0], [0.2, 0.2, 0.2]]
    _, outs = _check_all(_scene(means, _rand_quats(2, 3), scales, [0.6, 0.9]), grads=True)
    assert (outs["cpu"].alpha > 0.5).all()


def test_means_on_and_behind_the_near_plane():
    near = 0.125  # exact in float32, so the first mean lies exactly on the plane
    zs = [near, near * (1 - 1e-6), 0.0, -near, -5.0, near * (1 + 1e-6), 0.5, -1e-30]
    means = [[0.01 * i, 0.0, z] for i, z in enumerate(zs)]
    sc = _scene(means, _rand_quats(len(zs), 4), np.full((len(zs), 3), 0.05), np.full(len(zs), 0.9), near=near)
    _, outs = _check_all(sc, grads=True)
    culled = torch.tensor(zs, dtype=torch.float32).double() <= near
    assert culled.tolist() == [True, True, True, True, True, False, False, True]
    for out in outs.values():
        assert not out.visible[culled].any()
        assert (out.radii[culled] == 0).all()
        assert (out.n_contrib[culled] == 0).all()
    assert outs["cpu"].visible[~culled].all()


def test_camera_inside_a_gaussian():
    means = [[0.0, 0.0, 0.5], [0.1, 0.0, -0.3], [0.0, 0.2, 3.0]]
    scales = [[5.0, 4.0, 6.0], [5.0, 5.0, 5.0], [0.3, 0.3, 0.3]]
    _, outs = _check_all(_scene(means, _rand_quats(3, 6), scales, [0.5, 0.9, 0.8]), grads=True)
    assert outs["reference"].visible[0] and not outs["reference"].visible[1]


def stacked_layers(opacity: float, n: int = 10_000) -> RandomScene:
    """n coincident Gaussians along the optical axis of an 8x6 camera, front to back over z in [1, 3]."""
    return _scene(
        np.c_[np.zeros(n), np.zeros(n), np.linspace(1.0, 3.0, n)],
        np.tile([1.0, 0, 0, 0], (n, 1)),
        np.full((n, 3), 5.0),
        np.full(n, opacity),
        feats=np.random.default_rng(0).uniform(0, 1, (n, 3)),
        width=8,
        height=6,
        focal=4.0,
    )


@pytest.mark.parametrize("opacity", [1 - 1e-7, 0.02])
def test_ten_thousand_stacked_layers(opacity):
    """10,000 coincident Gaussians along the optical axis: early termination, no underflow, same decisions."""
    sc = stacked_layers(opacity)
    ref, outs = _check_all(sc, dtype=torch.float64)
    _check_all(sc, dtype=torch.float32)
    centre = outs["cpu"].alpha
    if opacity > 0.99:
        # Where alpha clamps to 0.99, two layers leave T = (1 - 0.99)^2, within 2e-16 of the 1e-4 threshold
        # (just above it in float64), so the second layer is blended and the third would cross it.
        clamped = (centre - (1 - 0.01**2)).abs() < 1e-12
        assert clamped.sum() >= 1
        for out in outs.values():
            assert (out.n_contrib[:2] == 8 * 6).all() and (out.n_contrib[2:] == 0).all()
    else:
        # 0.98^k reaches 1e-4 near k = 456: far fewer than 10,000 layers are ever blended.
        assert 300 < int((outs["cpu"].n_contrib > 0).sum()) < 600
    assert ref.n_contrib.sum() == int(outs["reference"].n_contrib.sum())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_denormal_quaternions_render_like_their_normalised_twin(dtype):
    tiny = 1e-40 if dtype == torch.float32 else 1e-310
    rng = np.random.default_rng(8)
    q = rng.normal(size=(6, 4))
    qd = torch.tensor(q * tiny, dtype=dtype)
    assert (qd.abs() < torch.finfo(dtype).tiny).any(), "the test needs denormal values"
    means = rng.normal(size=(6, 3)) * 0.3 + [0, 0, 3]
    sc = _scene(means, qd.double(), np.full((6, 3), [0.3, 0.05, 0.1]), np.full(6, 0.8))
    twin = sc._replace(quats=qd.double() / tiny)  # same direction, normal magnitude
    for backend in BACKENDS:
        a = rasterize(*sc.args(dtype), backend=backend)
        b = rasterize(*twin.args(torch.float64), backend=backend)
        _all_finite(a)
        assert (a.image.double() - b.image).abs().max() < 1e-5 * b.image.abs().max()


def test_zero_quaternion_is_rejected():
    sc = _scene([[0, 0, 3.0], [0, 0, 4.0]], [[1, 0, 0, 0], [0, 0, 0, 0]], np.full((2, 3), 0.1), [0.5, 0.5])
    for backend in BACKENDS:
        with pytest.raises(ValidationError, match=r"quats at index 1"):
            rasterize(*sc.args(), backend=backend)


@pytest.mark.parametrize("size", [(1, 1), (1, 37), (23, 1)])
def test_degenerate_image_sizes(size):
    w, h = size
    sc = random_scene(seed=w * 100 + h, n=25, d=4, width=w, height=h, focal=3.0, background=True)
    _check_all(sc, grads=True)


@pytest.mark.slow
def test_4096_square_image():
    sc = random_scene(seed=4096, n=6, d=3, width=4096, height=4096, focal=3000.0, log_scale=(-2.5, -1.0))
    _, outs = _check_all(sc)
    assert outs["cpu"].image.shape == (4096, 4096, 3)
    assert (outs["cpu"].alpha > 0).float().mean() > 0.01  # something was drawn


@pytest.mark.parametrize("focal", [1.0, 10.0, 1e3, 1e5, 1e6])
def test_extreme_focal_lengths(focal):
    sc = random_scene(seed=int(focal), n=30, d=3, width=32, height=24, focal=focal, background=True)
    ref, _ = _check_all(sc, grads=True)
    assert np.abs(ref.alpha).max() > 0  # the scene is in view at every focal length


def test_far_and_huge_values_stay_finite():
    means = [[1e30, 0, 1e30], [0, 0, 1e38], [0, 0, 3.0], [-3e38, 3e38, 5.0], [0.0, 0.0, 2.0]]
    scales = [[1.0, 1.0, 1.0], [1e30, 1e30, 1e30], [1e-30, 1e-30, 1e-30], [1.0, 1.0, 1.0], [1e20, 1.0, 1e-20]]
    _check_all(_scene(means, _rand_quats(5, 9), scales, [1.0, 0.5, 1.0, 0.7, 0.0]))


def test_opacity_extremes():
    rng = np.random.default_rng(2)
    means = rng.normal(size=(8, 3)) * 0.3 + [0, 0, 3]
    _check_all(_scene(means, _rand_quats(8, 1), np.full((8, 3), 0.2), [0, 1, 1, 0, 1e-30, 1 - 1e-16, 0.5, 1]))


FIELDS = ["means", "quats", "scales", "opacities", "features", "background"]


@pytest.mark.parametrize("field", FIELDS)
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
@pytest.mark.parametrize("backend", BACKENDS)
def test_non_finite_input_is_rejected_with_its_name(field, bad, backend):
    sc = random_scene(seed=1, n=6, d=3, width=8, height=8, focal=10.0, background=True)
    args = dict(
        means=sc.means,
        quats=sc.quats,
        scales=sc.scales,
        opacities=sc.opacities,
        features=sc.features,
        background=sc.background,
    )
    t = args[field].clone()
    if field == "background":
        t[1] = bad
        pattern = r"^background at index 1: contains NaN or Inf"
    else:
        t[4] = bad
        pattern = rf"^{field} at index 4: contains NaN or Inf"
    args[field] = t
    with pytest.raises(ValidationError, match=pattern):
        rasterize(
            args["means"],
            args["quats"],
            args["scales"],
            args["opacities"],
            args["features"],
            sc.camera,
            background=args["background"],
            backend=backend,
        )


def test_non_finite_camera_is_rejected():
    V = look_at([0, 0, -4.0], [0, 0, 0])
    V[1, 3] = float("nan")
    with pytest.raises(ValidationError, match="viewmat"):
        Camera(Camera.intrinsics(10, 10, 4, 4), V, 8, 8)
    with pytest.raises(ValidationError, match="K"):
        Camera(Camera.intrinsics(float("inf"), 10, 4, 4), torch.eye(4), 8, 8)
