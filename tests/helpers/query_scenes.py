"""A small queryable scene package (three blobs with their own embeddings) and a matching text encoder."""

from __future__ import annotations

import hashlib

import torch

from fmgs.cameras import Camera
from fmgs.field.hashgrid import HashGridConfig
from fmgs.field.model import FeatureField, FieldConfig
from fmgs.gaussians import GaussianSet
from fmgs.scene.package import export_scene
from fmgs.vecmath import safe_normalize

D = 16
N_PER = 60
CLASS_NAMES = ("red cube", "green ball", "blue cone")
CENTRES = torch.tensor([[-1.0, 0.0, 4.0], [1.0, 0.0, 4.0], [0.0, 1.0, 5.0]], dtype=torch.float64)
ENCODER_ID = "test/blob-encoder"


def class_vectors() -> torch.Tensor:
    """[3,D] unit vectors, one per class name."""
    g = torch.Generator().manual_seed(0)
    return safe_normalize(torch.randn(3, D, generator=g))


def blob_scene(folder, with_field: bool = False, seed: int = 0, scale: float = 0.15, opacity_logits=None):
    """Export the three-blob scene to ``folder``; returns (path, class vectors [3,D], canonical [4,D]).
    ``opacity_logits`` [N] replaces the uniform 2.0."""
    classes = class_vectors()
    g = torch.Generator().manual_seed(1 + seed)
    means, emb = [], []
    for i, c in enumerate(CENTRES):
        means.append(c.float() + 0.08 * torch.randn(N_PER, 3, generator=g))
        emb.append(safe_normalize(classes[i] + scale * torch.randn(N_PER, D, generator=g)))
    means = torch.cat(means)
    n = len(means)
    gs = GaussianSet(
        means,
        torch.randn(n, 4, generator=g),
        torch.full((n, 3), -3.0),
        torch.full((n,), 2.0) if opacity_logits is None else opacity_logits,
        0.3 * torch.randn(n, 4, 3, generator=g),
    )
    canon = FakeEncoder().encode_text(["object", "stuff", "things", "texture"])
    field = None
    if with_field:
        cfg = FieldConfig(HashGridConfig(levels=4, min_res=4, max_res=32, log2_table=12), D, 32, 2, 0)
        field = FeatureField.for_points(cfg, means)
    p = export_scene(
        folder, gs, torch.arange(n), torch.cat(emb), ENCODER_ID, canon, field=field,
        extra={"label_names": list(CLASS_NAMES)},
    )  # fmt: skip
    return p, classes, canon


class FakeEncoder:
    """Class names map to their class vectors; any other text to a seeded unit vector from its hash."""

    id = ENCODER_ID
    dim = D

    def encode_text(self, texts: list[str]) -> torch.Tensor:
        classes = class_vectors()
        out = []
        for t in texts:
            if t in CLASS_NAMES:
                out.append(classes[CLASS_NAMES.index(t)])
            else:
                seed = int.from_bytes(hashlib.sha256(t.encode()).digest()[:8], "little") % (2**63)
                out.append(safe_normalize(torch.randn(D, generator=torch.Generator().manual_seed(seed))))
        return torch.stack(out)


def camera(w: int = 48, h: int = 40) -> Camera:
    """Looks down +z from the origin at the blobs."""
    K = torch.tensor([[40.0, 0, w / 2], [0, 40.0, h / 2], [0, 0, 1]], dtype=torch.float64)
    return Camera(K, torch.eye(4, dtype=torch.float64), w, h)


def serve_process(models):
    """Start ``fmgs serve`` (the core's alias) on port 0 in a subprocess; returns (process, address)."""
    import subprocess

    from fmgs_server.launch import start_subprocess

    return start_subprocess(models, via_fmgs=True, stderr=subprocess.PIPE)
