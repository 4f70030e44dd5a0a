"""GaussianSet validation and spherical harmonics."""

from __future__ import annotations

import math

import pytest
import torch

from fmgs.errors import ValidationError
from fmgs.gaussians import SH_C0, GaussianSet
from fmgs.sh import eval_sh, sh_basis, sh_to_rgb


def _g(n=5, k=16, **over):
    t = dict(
        means=torch.randn(n, 3),
        quats=torch.randn(n, 4),
        log_scales=torch.randn(n, 3),
        opacity_logits=torch.randn(n),
        sh=torch.randn(n, k, 3),
    )
    t.update(over)
    return t


def test_valid_set_and_properties():
    g = GaussianSet(**_g())
    assert g.num == len(g) == 5 and g.sh_degree == 3
    assert torch.allclose(g.scales, torch.exp(g.log_scales))
    assert ((g.opacities > 0) & (g.opacities < 1)).all()
    sub = g.subset(torch.tensor([True, False, True, False, False]))
    assert sub.num == 2 and torch.equal(sub.means[1], g.means[2])


@pytest.mark.parametrize("field", ["means", "quats", "log_scales", "opacity_logits", "sh"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_is_rejected_with_field_and_index(field, bad):
    t = _g()
    t[field] = t[field].clone()
    t[field][3] = bad
    with pytest.raises(ValidationError, match=rf"^{field} at index 3: contains NaN or Inf"):
        GaussianSet(**t)


def test_zero_quaternion_rejected_denormal_accepted():
    t = _g()
    t["quats"] = t["quats"].clone()
    t["quats"][2] = 0.0
    with pytest.raises(ValidationError, match=r"^quats at index 2: zero quaternion"):
        GaussianSet(**t)
    t["quats"][2] = torch.tensor([1e-42, 0.0, 0.0, 0.0])
    assert t["quats"][2, 0] > 0  # float32 denormal
    GaussianSet(**t)


@pytest.mark.parametrize(
    ("over", "field"),
    [
        (dict(means=torch.randn(5, 2)), "means"),
        (dict(quats=torch.randn(4, 4)), "quats"),
        (dict(log_scales=torch.randn(5)), "log_scales"),
        (dict(opacity_logits=torch.randn(5, 1)), "opacity_logits"),
        (dict(sh=torch.randn(5, 5, 3)), "sh"),
        (dict(sh=torch.randn(5, 16, 4)), "sh"),
        (dict(means=torch.randn(5, 3, dtype=torch.float64)), "GaussianSet"),
    ],
)
def test_bad_shapes_are_named(over, field):
    with pytest.raises(ValidationError, match=rf"^{field}"):
        GaussianSet(**_g(**over))


def test_from_activated_round_trip():
    rgb = torch.rand(4, 3)
    g = GaussianSet.from_activated(
        torch.randn(4, 3), torch.randn(4, 4), torch.rand(4, 3) + 0.1, torch.rand(4) * 0.9 + 0.05, colors=rgb
    )
    assert g.sh_degree == 0
    assert torch.allclose(sh_to_rgb(g.sh, g.means, torch.zeros(3)), rgb, atol=1e-6)


def test_sh_basis_is_orthonormal():
    """Numerical integration over the sphere (Gauss-Legendre x uniform azimuth): <Y_i, Y_j> = delta_ij."""
    import numpy as np

    nt, nphi = 40, 80
    x, w = np.polynomial.legendre.leggauss(nt)
    phi = torch.arange(nphi, dtype=torch.float64) * (2 * math.pi / nphi)
    ct = torch.tensor(x).repeat_interleave(nphi)
    st = torch.sqrt(1 - ct**2)
    ph = phi.repeat(nt)
    dirs = torch.stack([st * torch.cos(ph), st * torch.sin(ph), ct], -1)
    weights = torch.tensor(w).repeat_interleave(nphi) * (2 * math.pi / nphi)
    Y = sh_basis(3, dirs)
    gram = (Y * weights[:, None]).T @ Y
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=1e-10)


def test_eval_sh_degrees_and_zero_direction():
    sh = torch.randn(7, 16, 3, dtype=torch.float64)
    dirs = torch.randn(7, 3, dtype=torch.float64)
    full = eval_sh(sh, dirs)
    manual = torch.einsum("nb,nbc->nc", sh_basis(3, dirs / dirs.norm(dim=-1, keepdim=True)), sh)
    assert torch.allclose(full, manual)
    dc = eval_sh(sh, dirs, degree=0)
    assert torch.allclose(dc, SH_C0 * sh[:, 0])
    # Scale invariance in the direction, and no NaN at a zero direction.
    assert torch.allclose(eval_sh(sh, 1e-200 * dirs), full)
    assert torch.isfinite(eval_sh(sh, torch.zeros(7, 3, dtype=torch.float64))).all()
    assert (sh_to_rgb(sh, torch.zeros(7, 3, dtype=torch.float64), torch.zeros(3)) >= 0).all()
