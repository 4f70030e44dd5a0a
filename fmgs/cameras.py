"""Pinhole cameras in the OpenCV convention (x right, y down, z forward).

``viewmat`` is the 4x4 world-to-camera transform and ``K`` the 3x3 intrinsics in pixels, with the
centre of pixel (row i, column j) at image coordinates (j + 0.5, i + 0.5), as COLMAP defines it.
Other conventions (COLMAP quaternions, OpenGL camera-to-world from ``transforms.json``) are converted
at the I/O boundary by the ``from_*`` constructors below.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from fmgs.checks import check_finite, check_shape
from fmgs.errors import ValidationError
from fmgs.vecmath import safe_normalize

# Rotation part of a viewmat must be orthonormal to this tolerance (float32 poses from files).
_ROT_TOL = 1e-4
# A c2w rotation part whose smallest singular value is below this fraction of its largest has lost a
# direction (a blank or degenerate pose): no orientation to recover by re-orthonormalising.
_SINGULAR_TOL = 1e-6
# OpenGL camera axes (x right, y up, z back) to OpenCV (x right, y down, z forward).
_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


@dataclass(frozen=True)
class Camera:
    """One pinhole camera.

    Tensors are float64 on the CPU; renderers move them where they need them.
    """

    K: torch.Tensor
    """[3,3] intrinsics in pixels: fx, fy on the diagonal, (cx, cy) in the last column."""
    viewmat: torch.Tensor
    """[4,4] world-to-camera rigid transform (OpenCV axes)."""
    width: int
    """Image width W in pixels (>= 1)."""
    height: int
    """Image height H in pixels (>= 1)."""
    near: float = 0.01
    """Gaussians whose mean has camera depth below this are culled."""
    far: float = 1e10
    """Gaussians whose mean has camera depth above this are culled."""
    name: str = field(default="", compare=False)
    """Optional label (e.g. the image file name)."""

    def __post_init__(self) -> None:
        K = torch.as_tensor(self.K, dtype=torch.float64).detach().cpu().clone()
        V = torch.as_tensor(self.viewmat, dtype=torch.float64).detach().cpu().clone()
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "viewmat", V)
        self.validate()

    def validate(self) -> None:
        """Raise ValidationError naming the first broken field."""
        check_shape("K", self.K, (3, 3))
        check_shape("viewmat", self.viewmat, (4, 4))
        # numpy views of the two small matrices: a camera per request (pose streams) stays cheap.
        K, V = self.K.numpy(), self.viewmat.numpy()
        if not (np.isfinite(K).all() and np.isfinite(V).all()):
            check_finite("K", self.K)
            check_finite("viewmat", self.viewmat)
        for name, v in (("width", self.width), ("height", self.height)):
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValidationError(name, f"must be a positive integer, got {v!r}")
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise ValidationError("K", "focal lengths fx, fy must be positive")
        if K[0, 1] != 0 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            raise ValidationError("K", "expected [[fx,0,cx],[0,fy,cy],[0,0,1]] (no skew)")
        if not (V[3] == (0.0, 0.0, 0.0, 1.0)).all():
            raise ValidationError("viewmat", "last row must be [0,0,0,1]")
        R = V[:3, :3]
        err = float(np.abs(R @ R.T - np.eye(3)).max())
        if err > _ROT_TOL or np.linalg.det(R) < 0:
            raise ValidationError(
                "viewmat", f"rotation is not a proper rotation (orthonormality error {err:.2e})"
            )
        if not (0 < self.near < self.far) or not math.isfinite(self.near):
            raise ValidationError("near", f"need 0 < near < far, got near={self.near}, far={self.far}")

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def camtoworld(self) -> torch.Tensor:
        """[4,4] camera-to-world transform (OpenCV axes)."""
        R = self.viewmat[:3, :3]
        t = self.viewmat[:3, 3]
        out = torch.eye(4, dtype=torch.float64)
        out[:3, :3] = R.T
        out[:3, 3] = -R.T @ t
        return out

    @property
    def center(self) -> torch.Tensor:
        """[3] camera centre in world coordinates."""
        return self.camtoworld[:3, 3]

    def scaled(self, factor: float) -> Camera:
        """The same camera with the image resized by ``factor`` (intrinsics scaled to match)."""
        return self.resized(max(1, round(self.width * factor)), max(1, round(self.height * factor)))

    def resized(self, w: int, h: int) -> Camera:
        """The same camera with the image resized to w x h pixels (intrinsics scaled per axis)."""
        if w < 1 or h < 1:
            raise ValidationError("size", f"image size must be positive, got {w}x{h}")
        sx, sy = w / self.width, h / self.height
        K = self.K.clone()
        K[0] *= sx
        K[1] *= sy
        K[2] = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        return Camera(K, self.viewmat, w, h, self.near, self.far, self.name)

    # ---- constructors from other conventions -------------------------------------------------------

    @staticmethod
    def intrinsics(fx: float, fy: float, cx: float, cy: float) -> torch.Tensor:
        """[3,3] K from focal lengths and principal point, in pixels."""
        return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)

    @classmethod
    def from_colmap(
        cls,
        qvec_wxyz: torch.Tensor | list[float],
        tvec: torch.Tensor | list[float],
        model: str,
        params: list[float],
        width: int,
        height: int,
        **kwargs,
    ) -> Camera:
        """A camera from a COLMAP image pose (world-to-camera, quaternion wxyz) and camera model.

        Only undistorted models are accepted here (PINHOLE, SIMPLE_PINHOLE, and the radial models
        with all distortion coefficients zero); undistort distorted images first.
        """
        q = torch.as_tensor(qvec_wxyz, dtype=torch.float64)
        t = torch.as_tensor(tvec, dtype=torch.float64)
        check_shape("qvec", q, (4,))
        check_shape("tvec", t, (3,))
        check_finite("qvec", q)
        check_finite("tvec", t)
        fx, fy, cx, cy = _colmap_pinhole_params(model, list(params))
        V = torch.eye(4, dtype=torch.float64)
        V[:3, :3] = quat_wxyz_to_rotmat(q)
        V[:3, 3] = t
        return cls(cls.intrinsics(fx, fy, cx, cy), V, int(width), int(height), **kwargs)

    @classmethod
    def from_opengl_c2w(cls, c2w: torch.Tensor, K: torch.Tensor, width: int, height: int, **kwargs) -> Camera:
        """A camera from an OpenGL camera-to-world matrix (NeRF / instant-ngp ``transforms.json``).

        c2w: [4,4] or [3,4] with camera x right, y up, z backwards.
        """
        M = torch.as_tensor(c2w, dtype=torch.float64)
        if M.shape == (3, 4):
            M = torch.cat([M, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)])
        check_shape("c2w", M, (4, 4))
        check_finite("c2w", M)
        c2w_cv = M @ _GL_TO_CV
        R = c2w_cv[:3, :3]
        # transforms.json files often carry scaled rotations; re-orthonormalise (SVD) before inverting.
        U, S, Vh = torch.linalg.svd(R)
        if not S[2] > _SINGULAR_TOL * S[0]:
            raise ValidationError(
                "c2w", f"rotation part is singular (singular values {S.tolist()}): no orientation"
            )
        R = U @ Vh
        if torch.det(R) < 0:
            raise ValidationError("c2w", "rotation part is a reflection")
        V = torch.eye(4, dtype=torch.float64)
        V[:3, :3] = R.T
        V[:3, 3] = -R.T @ c2w_cv[:3, 3]
        return cls(torch.as_tensor(K, dtype=torch.float64), V, int(width), int(height), **kwargs)


def quat_wxyz_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [...,3,3] from quaternions [...,4] (wxyz, any non-zero norm).

    Denormal quaternions normalise exactly (see safe_normalize).
    """
    w, x, y, z = safe_normalize(q).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


def _colmap_pinhole_params(model: str, p: list[float]) -> tuple[float, float, float, float]:
    """fx, fy, cx, cy of a COLMAP camera whose distortion is zero; error for any other."""

    def need(n: int) -> None:
        if len(p) != n:
            raise ValidationError("params", f"COLMAP model {model} takes {n} parameters, got {len(p)}")

    if model == "PINHOLE":
        need(4)
        return p[0], p[1], p[2], p[3]
    if model == "SIMPLE_PINHOLE":
        need(3)
        return p[0], p[0], p[1], p[2]
    radial = {"SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8, "FULL_OPENCV": 12}
    if model in radial:
        need(radial[model])
        simple = model in ("SIMPLE_RADIAL", "RADIAL")
        fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if simple else (p[0], p[1], p[2], p[3])
        dist = p[3:] if simple else p[4:]
        if any(d != 0 for d in dist):
            raise ValidationError(
                "model", f"COLMAP model {model} has non-zero distortion {dist}; undistort the images first"
            )
        return fx, fy, cx, cy
    raise ValidationError("model", f"unsupported COLMAP camera model {model!r}; undistort to PINHOLE first")
