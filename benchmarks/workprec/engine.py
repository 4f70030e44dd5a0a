"""The product path: a scene package opened by SceneEngine exactly as the query server opens it.

The default point of the text and pose sections is measured through this engine, so the report's
"default" is what ``fmgs serve`` answers with, not a re-assembly of its parts.
"""

from __future__ import annotations

from pathlib import Path

import torch

from benchmarks.common import export
from fmgs.gaussians import GaussianSet
from fmgs.query.engine import EngineConfig, SceneEngine


def server_engine_config() -> EngineConfig:
    """The EngineConfig that fmgs_server.server.start_server builds from a default ServerConfig."""
    from fmgs_server.config import ServerConfig

    cfg = ServerConfig()
    return EngineConfig(cfg.index, device=cfg.device)


def product_engine(
    folder: Path, gaussians: GaussianSet, embeddings: torch.Tensor, canonical: torch.Tensor
) -> SceneEngine:
    """Export every Gaussian with its embedding [N,D] to the package ``folder`` (float16 embeddings,
    canonical dots from them; benchmarks/common.py ``export``), then open it as the server does."""
    export(folder, gaussians, embeddings, canonical)
    return SceneEngine.open(folder, server_engine_config())
