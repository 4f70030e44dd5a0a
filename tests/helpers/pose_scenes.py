"""Field-like scenes for pose-query tests: exported packages, a camera looking at them, and the float64
dot-then-render reference their relevancy images are held to."""

from __future__ import annotations

import torch

from benchmarks.query_sets import scene_embeddings
from fmgs.cameras import Camera
from fmgs.gaussians import GaussianSet
from fmgs.query.relevancy import TEMPERATURE, relevancy
from fmgs.render import rasterize
from fmgs.scene.package import export_scene
from fmgs.vecmath import safe_normalize

SETS = ("near", "typical", "clip", "absent")
"""benchmarks/query_sets.py's sets an image is checked on (ties behave as near)."""


def fieldlike_package(folder, n: int, dim: int, scale: float):
    """A field-like scene of n Gaussians in the unit cube, exported (float16 embeddings) -> (path,
    embeddings [n,D] float16, rows that are copies)."""
    g = torch.Generator().manual_seed(0)
    means = torch.rand(n, 3, generator=g)
    gs = GaussianSet.from_activated(
        means, torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4), torch.full((n, 3), scale), torch.full((n,), 0.5)
    )
    emb, copies = scene_embeddings(n, dim, seed=1, means=means, dtype=torch.float16)
    canon = safe_normalize(torch.randn(4, dim, generator=g))
    return export_scene(folder, gs, torch.arange(n), emb, "test/pose", canon), emb, copies


def cube_camera(x: float = 0.5, y: float = 0.5, dist: float = 1.2, size=(64, 48), f: float = 60.0) -> Camera:
    """A camera at (x, y, -dist) looking along +z at the unit cube (OpenCV axes), focal f pixels."""
    V = torch.eye(4, dtype=torch.float64)
    V[:3, 3] = torch.tensor([-x, -y, dist], dtype=torch.float64)
    W, H = size
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]], dtype=torch.float64)
    return Camera(K, V, W, H)


def dot_then_render_reference(engine, emb: torch.Tensor, q: torch.Tensor, cam: Camera) -> torch.Tensor:
    """[H,W] float64 dot-then-render reference: every Gaussian's float64 f.q (from the stored float16
    embeddings) and stored canonical dots, blended in float64 on the reference backend, scored in float64."""
    qq = engine.unit(q[None])[0].double()
    chans = torch.cat([(emb.double() @ qq)[:, None], engine.index.canonical.double()], 1)
    geom = [t.double() for t in engine.geometry]
    img = rasterize(*geom, chans, cam, backend="reference").image
    return relevancy(img[..., 0], img[..., 1:], TEMPERATURE)
