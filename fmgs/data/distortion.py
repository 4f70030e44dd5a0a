"""The OpenCV lens model (radial k1, k2, k3 and tangential p1, p2) on normalised image coordinates.

COLMAP's OPENCV / FULL_OPENCV cameras and the instant-ngp / nerfstudio ``transforms.json`` keys use it.
The datasets are undistorted by pycolmap; these functions make distorted test scenes (``fmgs synth``)
and check the undistortion against the model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class OpenCVDistortion:
    """Coefficients of x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + tangential(p1, p2), r^2 = x^2 + y^2."""

    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    @property
    def is_zero(self) -> bool:
        return not any((self.k1, self.k2, self.p1, self.p2, self.k3))

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ideal (pinhole) normalised coordinates [...] -> distorted ones [...]."""
        r2 = x * x + y * y
        radial = 1 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        xd = x * radial + 2 * self.p1 * x * y + self.p2 * (r2 + 2 * x * x)
        yd = y * radial + self.p1 * (r2 + 2 * y * y) + 2 * self.p2 * x * y
        return xd, yd

    def undistort(
        self, xd: np.ndarray, yd: np.ndarray, iterations: int = 100, tol: float = 1e-14
    ) -> tuple[np.ndarray, np.ndarray]:
        """Inverse of ``distort`` by Newton's method on the 2x2 Jacobian (converges where the lens
        model is monotonic, i.e. inside the image of any sane calibration)."""
        x, y = np.array(xd, dtype=np.float64), np.array(yd, dtype=np.float64)
        for _ in range(iterations):
            fx, fy = self.distort(x, y)
            ex, ey = fx - xd, fy - yd
            if max(np.abs(ex).max(initial=0.0), np.abs(ey).max(initial=0.0)) < tol:
                break
            h = 1e-7
            ax, ay = self.distort(x + h, y)
            bx, by = self.distort(x, y + h)
            j00, j10 = (ax - fx) / h, (ay - fy) / h
            j01, j11 = (bx - fx) / h, (by - fy) / h
            det = j00 * j11 - j01 * j10
            x = x - (j11 * ex - j01 * ey) / det
            y = y - (-j10 * ex + j00 * ey) / det
        return x, y
