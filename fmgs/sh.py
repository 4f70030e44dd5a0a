"""Real spherical harmonics to degree 3, in the ordering and sign convention of graphdeco 3DGS."""

from __future__ import annotations

import torch

from fmgs.gaussians import SH_C0, sh_degree_from_bases
from fmgs.vecmath import safe_normalize

_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """SH basis values [...,(degree+1)^2] at unit directions ``dirs`` [...,3]."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [
            _C2[0] * xy,
            _C2[1] * yz,
            _C2[2] * (2 * zz - xx - yy),
            _C2[3] * xz,
            _C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            _C3[0] * y * (3 * xx - yy),
            _C3[1] * xy * z,
            _C3[2] * y * (4 * zz - xx - yy),
            _C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            _C3[4] * x * (4 * zz - xx - yy),
            _C3[5] * z * (xx - yy),
            _C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor, degree: int | None = None) -> torch.Tensor:
    """Raw SH colour [N,3] from coefficients [N,K,3] along directions [N,3] (need not be unit).

    Uses the first (degree+1)^2 coefficients (all of them by default). A zero direction evaluates
    only the DC term's direction-independent part (no NaN).
    """
    max_deg = sh_degree_from_bases(sh.shape[1])
    degree = max_deg if degree is None else min(degree, max_deg)
    unit = safe_normalize(dirs)
    basis = sh_basis(degree, unit)  # [N,B]
    return torch.einsum("nb,nbc->nc", basis, sh[:, : basis.shape[-1]])


def sh_to_rgb(
    sh: torch.Tensor, means: torch.Tensor, cam_center: torch.Tensor, degree: int | None = None
) -> torch.Tensor:
    """View-dependent RGB [N,3] seen from ``cam_center`` [3]: SH + 0.5, clamped at 0 (graphdeco)."""
    dirs = means - cam_center.to(means)
    return (eval_sh(sh, dirs, degree) + 0.5).clamp_min(0.0)
