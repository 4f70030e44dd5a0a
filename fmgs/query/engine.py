"""A scene ready for queries: compact per-Gaussian state, render geometry, typed answers.

The engine works on embedding vectors; turning texts into vectors (and checking the encoder) is the
caller's job, so the same engine serves any text encoder the scene was trained with.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import torch

from fmgs.errors import ValidationError
from fmgs.query.index import EmbeddingIndex, IndexConfig
from fmgs.query.instances import Instance, InstanceConfig, default_eps, group_instances
from fmgs.scene.package import ScenePackage, load_scene
from fmgs.vecmath import safe_normalize


@dataclass(frozen=True)
class EngineConfig:
    """How a scene is held and answered."""

    index: IndexConfig = field(default_factory=IndexConfig)
    """Per-Gaussian query state (exact or compact)."""
    backend: str = "auto"
    """Rasteriser backend for pose queries ("auto", "cpu", "reference", "cuda")."""
    device: str = "cpu"
    """Device holding the render geometry."""


class TextAnswer(NamedTuple):
    """Gaussians ranked for one query, with optional instances."""

    index: torch.Tensor
    """[K] int64 scene indices (into all Gaussians), most relevant first."""
    relevancy: torch.Tensor
    """[K] float32 relevancy in (0,1)."""
    similarity: torch.Tensor
    """[K] float32 cosine similarity with the query."""
    instances: list[Instance]
    """Object instances among the K Gaussians, best first (empty unless asked)."""
    instance_ids: np.ndarray | None
    """[K] int32 instance of each Gaussian (-1 none), or None unless instances were asked for."""


class SceneEngine:
    """Everything a server needs to answer queries on one scene."""

    def __init__(self, package: ScenePackage, cfg: EngineConfig = EngineConfig()) -> None:
        self.name = package.name
        self.manifest = package.manifest
        self.cfg = cfg
        self.dim = package.dim
        self.encoder_id = package.encoder_id
        self.canonical_phrases = tuple(package.canonical_phrases)
        self.field = package.field
        g = package.gaussians
        self.gaussians = g.to(cfg.device)
        """All Gaussians (RGB and depth renders)."""
        self.selected = package.selected.cpu()
        """[M] int64 scene indices of the embedded Gaussians."""
        sub = self.gaussians.subset(package.selected.to(self.gaussians.device))
        self.geometry = (sub.means, sub.quats, sub.scales.float(), sub.opacities.float())
        """Activated geometry of the embedded Gaussians (relevancy renders)."""
        self.index = EmbeddingIndex.build(package.embeddings, package.canonical, cfg.index)
        means = g.means.detach().cpu().double().numpy()
        self.bounds = np.concatenate([means.min(0), means.max(0)]) if len(means) else np.zeros(6, np.float64)
        """[6] min xyz, max xyz of all means."""
        self._eps = default_eps(means, InstanceConfig().eps_fraction)

    @classmethod
    def open(cls, path, cfg: EngineConfig = EngineConfig()) -> SceneEngine:
        """Load a package with its embeddings memory-mapped (only the query state is resident)."""
        return cls(load_scene(path, mmap=cfg.device == "cpu"), cfg)

    @property
    def num_gaussians(self) -> int:
        return self.gaussians.num

    @property
    def num_embedded(self) -> int:
        return len(self.selected)

    def nbytes(self) -> int:
        """Resident bytes: query state, geometry and the field."""
        n = self.index.nbytes() + self.selected.numel() * 8
        n += sum(t.numel() * t.element_size() for t in self.gaussians.tensors().values())
        n += sum(t.numel() * t.element_size() for t in self.geometry)
        if self.field is not None:
            n += sum(p.numel() * p.element_size() for p in self.field.state_dict().values())
        return n

    def unit(self, vectors: torch.Tensor, what: str = "query embedding") -> torch.Tensor:
        """[n,D] finite non-zero vectors, unit-normalised; ValidationError names ``what`` otherwise."""
        v = torch.as_tensor(vectors)
        if v.ndim != 2 or v.shape[1] != self.dim:
            raise ValidationError(what, f"expected [n,{self.dim}], got {list(v.shape)}")
        v = v.float()
        if not bool(torch.isfinite(v).all()) or bool((v.abs().amax(1) == 0).any()):
            raise ValidationError(what, "must be finite and non-zero")
        return safe_normalize(v)

    @torch.no_grad()
    def text_query(
        self,
        query: torch.Tensor,
        top_k: int,
        threshold: float = 0.0,
        canonical: torch.Tensor | None = None,
        instances: InstanceConfig | None = None,
    ) -> TextAnswer:
        """Rank the embedded Gaussians for query [D]; canonical [C,D] replaces the scene's phrases."""
        q = self.unit(query[None])[0]
        c = None if canonical is None else self.unit(canonical, "canonical embeddings")
        r = self.index.rank(q, top_k, threshold, c)
        idx = self.selected[r.rows]
        inst, ids = [], None
        if instances is not None:
            g = self.gaussians
            means = g.means[idx].detach().cpu().double().numpy()
            opac = g.opacities[idx].detach().cpu().double().numpy()
            eps = instances.eps or self._eps_for(instances)
            inst, ids = group_instances(means, r.relevancy.numpy(), opac, instances, eps)
        return TextAnswer(idx, r.relevancy, r.similarity, inst, ids)

    def _eps_for(self, cfg: InstanceConfig) -> float:
        if cfg.eps_fraction == InstanceConfig().eps_fraction:
            return self._eps
        return default_eps(self.gaussians.means.detach().cpu().double().numpy(), cfg.eps_fraction)

    def channels(self, vectors: torch.Tensor) -> torch.Tensor:
        """[M,n] f.v per embedded Gaussian for unit vectors [n,D] (the index's dots)."""
        return self.index.dots(vectors)
