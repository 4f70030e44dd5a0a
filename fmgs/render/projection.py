"""EWA projection of 3D Gaussians to screen space, in float64 and differentiable.

Computed in float64 whatever the input dtype: the later blending makes discrete choices
(alpha >= alpha_min, transmittance >= transmittance_min) and float64 geometry lets every backend make
the same choices, so float32 outputs agree with the float64 reference to rounding error.
"""

from __future__ import annotations

import torch

from fmgs.cameras import Camera, quat_wxyz_to_rotmat
from fmgs.render.types import Projection, RasterConfig

# Bound on the entries of the 2x3 screen-space factor M; keeps every product below ~1e300.
_M_LIMIT = 1e75
# Relative and absolute slack on the culling box, so float64 rounding never culls a contributor.
_BOX_REL, _BOX_ABS = 1e-6, 1e-6


def covariance_factor(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """[N,3,3] L = R(q) diag(s), so the world covariance is L L^T."""
    return quat_wxyz_to_rotmat(quats) * scales.unsqueeze(-2)


def project(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    camera: Camera,
    config: RasterConfig,
) -> Projection:
    """Project N Gaussians (means [N,3], quats [N,4] wxyz, scales [N,3], opacities [N]) for a camera."""
    f64 = torch.float64
    dev = means.device
    means, quats, scales, opacities = (t.to(f64) for t in (means, quats, scales, opacities))
    V = camera.viewmat.to(dev)
    R, t = V[:3, :3], V[:3, 3]
    p = means @ R.T + t
    z = p[:, 2]
    in_depth = (z > camera.near) & (z < camera.far)
    z_safe = torch.where(in_depth, z, torch.ones_like(z))  # no inf/NaN in masked rows, even in grads

    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    W, H = camera.width, camera.height
    tan_x, tan_y = 0.5 * W / fx, 0.5 * H / fy
    lim_xp, lim_xn = (W - cx) / fx + config.fov_clip * tan_x, cx / fx + config.fov_clip * tan_x
    lim_yp, lim_yn = (H - cy) / fy + config.fov_clip * tan_y, cy / fy + config.fov_clip * tan_y
    tx = z_safe * torch.clamp(p[:, 0] / z_safe, -lim_xn, lim_xp)
    ty = z_safe * torch.clamp(p[:, 1] / z_safe, -lim_yn, lim_yp)
    zero = torch.zeros_like(z_safe)
    J = torch.stack(
        [
            torch.stack([fx / z_safe, zero, -fx * tx / z_safe**2], -1),
            torch.stack([zero, fy / z_safe, -fy * ty / z_safe**2], -1),
        ],
        dim=-2,
    )  # [N,2,3]
    M = (J @ R) @ covariance_factor(quats, scales)  # [N,2,3]; 2D covariance = M M^T
    M = M.clamp(-_M_LIMIT, _M_LIMIT)
    m0, m1 = M[:, 0], M[:, 1]
    a_raw = (m0 * m0).sum(-1)
    b = (m0 * m1).sum(-1)
    c_raw = (m1 * m1).sum(-1)
    # Cauchy-Binet: det(M M^T) as a sum of squared 2x2 minors, never negative, no cancellation of a*c - b^2.
    minors = torch.stack(
        [
            m0[:, 0] * m1[:, 1] - m0[:, 1] * m1[:, 0],
            m0[:, 0] * m1[:, 2] - m0[:, 2] * m1[:, 0],
            m0[:, 1] * m1[:, 2] - m0[:, 2] * m1[:, 1],
        ],
        -1,
    )
    eps = config.eps2d
    det = (minors * minors).sum(-1) + eps * (a_raw + c_raw) + eps * eps
    a, c = a_raw + eps, c_raw + eps
    conics = torch.stack([c / det, -b / c, 1.0 / c], -1)  # completed square: see Projection.conics

    u = fx * p[:, 0] / z_safe + cx
    v = fy * p[:, 1] / z_safe + cy
    means2d = torch.stack([u, v], -1)

    with torch.no_grad():
        radii, bbox, visible = _extent(u, v, a, b, c, opacities, in_depth, W, H, config)
    return Projection(means2d, z, conics, opacities, radii, bbox, visible)


def _extent(u, v, a, b, c, opac, in_depth, W: int, H: int, config: RasterConfig):
    """3-sigma radii and the conservative pixel box where alpha can reach alpha_min."""
    lam_max = 0.5 * (a + c) + torch.sqrt((0.5 * (a - c)) ** 2 + b * b)
    radius = torch.ceil(3.0 * torch.sqrt(lam_max))
    # alpha = o exp(-power/2) >= alpha_min  <=>  power <= r2;
    # the ellipse's bounding box has half-widths r sqrt(a), r sqrt(c).
    ratio = (opac / config.alpha_min).clamp_min(1.0)
    r2 = 2.0 * torch.log(ratio)
    hx = torch.sqrt(r2 * a) * (1 + _BOX_REL) + _BOX_ABS
    hy = torch.sqrt(r2 * c) * (1 + _BOX_REL) + _BOX_ABS
    # Pixel j is sampled at j + 0.5: include j when |j + 0.5 - u| <= hx. Clamp before casting to ints.
    x0 = torch.ceil((u - hx - 0.5).clamp(-1.0, W + 1.0))
    x1 = torch.floor((u + hx - 0.5).clamp(-2.0, W + 1.0))
    y0 = torch.ceil((v - hy - 0.5).clamp(-1.0, H + 1.0))
    y1 = torch.floor((v + hy - 0.5).clamp(-2.0, H + 1.0))
    x0, y0 = x0.clamp_min(0), y0.clamp_min(0)
    x1, y1 = x1.clamp_max(W - 1), y1.clamp_max(H - 1)
    can_hit = opac >= config.alpha_min
    visible = in_depth & can_hit & (x0 <= x1) & (y0 <= y1)
    bbox = torch.stack([x0, y0, x1, y1], -1).to(torch.int64)
    radius_i = torch.where(visible, radius.clamp(0, 2**31 - 1), torch.zeros_like(radius)).to(torch.int32)
    return radius_i, bbox, visible


def gaussian_alpha(power: torch.Tensor, opac: torch.Tensor, config: RasterConfig) -> torch.Tensor:
    """alpha = min(alpha_max, o exp(-power/2)), zeroed below alpha_min (the blending rule's first step)."""
    alpha = torch.clamp(opac * torch.exp(-0.5 * power), max=config.alpha_max)
    return torch.where(alpha >= config.alpha_min, alpha, torch.zeros_like(alpha))
