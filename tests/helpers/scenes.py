"""Random scenes for the agreement and stiff-case suites."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from fmgs.cameras import Camera


class RandomScene(NamedTuple):
    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    features: torch.Tensor
    camera: Camera
    background: torch.Tensor | None

    def args(self, dtype=torch.float32):
        f = lambda t: t.to(dtype)  # noqa: E731
        return (
            f(self.means),
            f(self.quats),
            f(self.scales),
            f(self.opacities),
            f(self.features),
            self.camera,
        )

    def brute_args(self, dtype=torch.float32):
        """The same inputs, cast to ``dtype`` first, as numpy for the brute force."""
        m, q, s, o, f, cam = self.args(dtype)
        return dict(
            means=m.numpy(),
            quats=q.numpy(),
            scales=s.numpy(),
            opacities=o.numpy(),
            features=f.numpy(),
            K=cam.K.numpy(),
            viewmat=cam.viewmat.numpy(),
            width=cam.width,
            height=cam.height,
            near=cam.near,
            far=cam.far,
            background=None if self.background is None else self.background.to(dtype).numpy(),
        )


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> torch.Tensor:
    """[4,4] world-to-camera for an OpenCV camera at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    V = np.eye(4)
    V[:3, :3] = R
    V[:3, 3] = -R @ eye
    return torch.from_numpy(V)


def random_scene(
    seed: int,
    n: int,
    d: int,
    width: int,
    height: int,
    focal: float,
    log_scale: tuple[float, float] = (-3.5, -0.5),
    background: bool = False,
    spread: float = 1.0,
) -> RandomScene:
    """n Gaussians in a ball of radius ``spread`` about the origin, seen from a random point at distance 4."""
    rng = np.random.default_rng(seed)
    means = rng.normal(size=(n, 3)) * spread / 2
    quats = rng.normal(size=(n, 4))
    scales = np.exp(rng.uniform(*log_scale, size=(n, 3)))
    opac = rng.uniform(0.0, 1.0, size=n)
    feats = rng.normal(size=(n, d))
    eye = rng.normal(size=3)
    eye = 4.0 * eye / np.linalg.norm(eye)
    target = rng.normal(size=3) * 0.2
    K = Camera.intrinsics(
        focal, focal * rng.uniform(0.8, 1.25), width * rng.uniform(0.3, 0.7), height * rng.uniform(0.3, 0.7)
    )
    cam = Camera(K, look_at(eye, target), width, height)
    t = lambda a: torch.from_numpy(np.asarray(a))  # noqa: E731
    bg = t(rng.normal(size=d)) if background else None
    return RandomScene(t(means), t(quats), t(scales), t(opac), t(feats), cam, bg)


def surface_ply(scene, out, scale: float = 0.04) -> None:
    """A '3DGS scene trained elsewhere' for a generated dataset: small opaque Gaussians on its surface
    samples, coloured like them. (Geometry training is tested in test_train_gs; this keeps end-to-end
    tests fast.)"""
    from fmgs.data.dataset import load_dataset
    from fmgs.gaussians import GaussianSet
    from fmgs.io.ply import write_ply

    ds = load_dataset(scene)
    pts = torch.from_numpy(ds.points).float()
    cols = torch.from_numpy(ds.colors).float() / 255
    n = len(pts)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1)
    g = GaussianSet.from_activated(pts, quats, torch.full((n, 3), scale), torch.full((n,), 0.9), cols)
    write_ply(g, out)
