"""Benchmark scenes: the real garden point set and synthetic scenes of any size."""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from benchmarks.common import ROOT
from fmgs.cameras import Camera

DATA = Path(os.environ.get("FMGS_DATA", ROOT.parent / "shared" / "data"))


class Scene(NamedTuple):
    means: torch.Tensor  # [N,3]
    quats: torch.Tensor  # [N,4]
    scales: torch.Tensor  # [N,3]
    opacities: torch.Tensor  # [N]
    colors: torch.Tensor  # [N,3] in [0,1]
    cameras: list[Camera]
    name: str


def garden(opacity: float = 0.8, knn: int = 3) -> Scene:
    """gsplat's test_garden points with isotropic scales = mean distance to the ``knn`` nearest neighbours."""
    from scipy.spatial import cKDTree

    d = np.load(DATA / "gsplat_test_garden" / "test_garden.npz")
    means = d["means3d"].astype(np.float32)
    dist, _ = cKDTree(means).query(means, k=knn + 1)
    s = dist[:, 1:].mean(1).clip(1e-7).astype(np.float32)
    n = len(means)
    W, H = int(d["width"]), int(d["height"])
    cams = [
        Camera(torch.from_numpy(K.astype(np.float64)), torch.from_numpy(V.astype(np.float64)), W, H)
        for K, V in zip(d["Ks"], d["viewmats"], strict=True)
    ]
    return Scene(
        torch.from_numpy(means),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        torch.from_numpy(np.repeat(s[:, None], 3, 1)),
        torch.full((n,), opacity),
        torch.from_numpy(d["colors"].astype(np.float32) / 255.0),
        cams,
        "garden",
    )


def synthetic(n: int, seed: int = 0, width: int = 648, height: int = 420) -> Scene:
    """n anisotropic Gaussians filling a box in front of three cameras; sizes scale with n^(-1/3)."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([8.0, 5.0, 6.0]) + torch.tensor(
        [0.0, 0.0, 8.0]
    )
    quats = torch.randn(n, 4, generator=g)
    base = 3.0 * n ** (-1.0 / 3.0)
    scales = base * torch.exp(torch.randn(n, 3, generator=g) * 0.4)
    opac = torch.rand(n, generator=g) * 0.8 + 0.1
    colors = torch.rand(n, 3, generator=g)
    f = 0.9 * width
    K = Camera.intrinsics(f, f, width / 2, height / 2)
    cams = []
    for ang in (-0.15, 0.0, 0.15):
        V = torch.eye(4, dtype=torch.float64)
        c, s = np.cos(ang), np.sin(ang)
        V[:3, :3] = torch.tensor([[c, 0, -s], [0, 1, 0], [s, 0, c]], dtype=torch.float64)
        V[:3, 3] = torch.tensor([-8.0 * s, 0.0, 8.0 - 8.0 * c], dtype=torch.float64)
        cams.append(Camera(K, V, width, height))
    return Scene(means, quats, scales, opac, colors, cams, f"synthetic-{n}")


def view(scene: str, width: int, height: int, opacity: float = 0.8):
    """(means, quats, scales, opacities, camera) of a named scene at a size: 'garden' (every Gaussian at
    ``opacity``, view 0 resized to ``width`` and centre-cropped to ``height``) or 'synthetic-<N>' (its
    middle camera; synthetic scenes draw their opacities)."""
    if scene == "garden":
        s = garden(opacity=opacity)
        cam = s.cameras[0]
        f = width / cam.width
        K = cam.K.clone()
        K[:2] *= f
        # Resize to the requested width, then centre-crop the rows to the requested height.
        K[1, 2] -= (round(cam.height * f) - height) / 2
        cam = Camera(K, cam.viewmat, width, height)
        return s.means, s.quats, s.scales, s.opacities, cam
    n = int(scene.split("-")[1])
    s = synthetic(n, width=width, height=height)
    return s.means, s.quats, s.scales, s.opacities, s.cameras[1]
