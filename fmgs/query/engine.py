"""A scene ready for queries: compact per-Gaussian state, render geometry, typed answers.

The engine works on embedding vectors; turning texts into vectors (and checking the encoder) is the
caller's job, so the same engine serves any text encoder the scene was trained with.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
import torch

from fmgs.cameras import Camera
from fmgs.errors import ValidationError
from fmgs.gaussians import SH_C0
from fmgs.query.index import EmbeddingIndex, IndexConfig
from fmgs.query.instances import Instance, InstanceConfig, default_eps, group_instances
from fmgs.query.pose import render_pose
from fmgs.query.presence import Presence, PresenceConfig, Probe, presence
from fmgs.scene.package import ScenePackage, load_scene
from fmgs.vecmath import safe_normalize


@dataclass(frozen=True)
class EngineConfig:
    """How a scene is held and answered."""

    index: IndexConfig = field(default_factory=IndexConfig)
    """Per-Gaussian query state (exact or compact)."""
    backend: str = "auto"
    """Rasteriser backend for pose queries ("auto", "cpu", "reference", "cuda", "triton")."""
    device: str = "cpu"
    """Device holding the render geometry; a CUDA device also holds the query state (exact float32)."""


GAUSSIAN_COLUMNS = ("mean", "opacity", "scale", "rotation", "color")
"""Per-Gaussian attributes a text answer can carry (SceneEngine.gaussian_columns)."""


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
    rescored: int = 0
    """Gaussians scored exactly to certify the ranking (fmgs.query.certify)."""
    presence: Presence | None = None
    """Is the queried thing in the scene (fmgs.query.presence); None unless negatives were given."""
    columns: dict[str, np.ndarray] | None = None
    """Gaussian columns carried with the answer (sharded scenes); None: ask the engine."""


PRESENCE = PresenceConfig()
"""The default presence settings."""
NO_GAUSSIANS = Presence(0.0, False, -2.0, -1)
"""The presence of any query in a scene without embedded Gaussians (-2: the least margin of unit vectors)."""


class _Channels:
    """One query's relevancy channels [M,1+C] float32 and, on the compact path, which rows hold exact
    values yet (``scored`` [M] bool; None when every row does). Filled under ``lock``."""

    __slots__ = ("lock", "scored", "values")

    def __init__(self, values: torch.Tensor, scored: np.ndarray | None) -> None:
        self.values, self.scored, self.lock = values, scored, threading.Lock()


class SceneEngine:
    """Everything a server needs to answer queries on one scene."""

    CHANNEL_CACHE = 8
    """Relevancy channel sets kept for repeated queries ([M,5] float32 each, and on the compact path an
    [M] mask of the rows scored so far)."""

    def __init__(self, package: ScenePackage, cfg: EngineConfig = EngineConfig()) -> None:
        self._chan_cache: OrderedDict[bytes, _Channels] = OrderedDict()
        self._cache_lock = threading.Lock()
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
        icfg = cfg.index if cfg.device == "cpu" else replace(cfg.index, device=cfg.device)
        self.index = EmbeddingIndex.build(
            package.embeddings, package.canonical, icfg, state=package.query_state
        )
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
        per_row = (1 + self.index.canonical.shape[1]) * 4 + (0 if self.index.exact else 1)
        return n + self.CHANNEL_CACHE * self.num_embedded * per_row

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
        negatives: torch.Tensor | None = None,
        presence_cfg: PresenceConfig = PRESENCE,
        probe: Probe | None = None,
    ) -> TextAnswer:
        """Rank the embedded Gaussians for query [D]; canonical [C,D] replaces the scene's phrases;
        negatives [V,D] (the scene's text encoder's embeddings of ``presence.negative_names``) add a
        presence score, decided with ``probe`` (fmgs.query.presence.probes) when given."""
        return self.text_query_many(
            query[None],
            top_k,
            threshold,
            canonical,
            instances,
            negatives=negatives,
            presence_cfg=presence_cfg,
            probes=None if probe is None else [probe],
        )[0]

    @torch.no_grad()
    def text_query_many(
        self,
        queries: torch.Tensor,
        top_k: int,
        threshold: float = 0.0,
        canonical: torch.Tensor | None = None,
        instances: InstanceConfig | None = None,
        between: Callable[[int], None] | None = None,
        negatives: torch.Tensor | None = None,
        presence_cfg: PresenceConfig = PRESENCE,
        probes: Sequence[Probe] | None = None,
    ) -> list[TextAnswer]:
        """``text_query`` for queries [n,D], scored in one pass over the query state; ``between(j)`` runs
        before text j is ranked (a deadline check may raise there); probes [n] as ``text_query``'s."""
        q = self.unit(queries)
        if probes is not None and len(probes) != len(q):
            raise ValidationError("probes", f"{len(probes)} presence probes for {len(q)} queries")
        c = None if canonical is None else self.unit(canonical, "canonical embeddings")
        neg = None if negatives is None else self.unit(negatives, "negative embeddings")
        # Presence needs the best presence_cfg.rows rows: one ranking serves both unless a threshold
        # cuts the answer shorter.
        k = top_k if neg is None or threshold > 0 else max(top_k, presence_cfg.rows)
        ranked = self.index.rank_many(q, k, threshold, c, between)
        presences = (
            [None] * len(q) if neg is None else self._presence(q, ranked, c, neg, presence_cfg, probes)
        )
        out = []
        for r, pres in zip(ranked, presences, strict=True):
            r = r._replace(
                rows=r.rows[:top_k], relevancy=r.relevancy[:top_k], similarity=r.similarity[:top_k]
            )
            idx = self.selected[r.rows]
            inst, ids = [], None
            if instances is not None:
                means, opac = self.instance_inputs(idx)
                eps = instances.eps or self._eps_for(instances)
                inst, ids = group_instances(means, r.relevancy.numpy(), opac, instances, eps)
            out.append(TextAnswer(idx, r.relevancy, r.similarity, inst, ids, r.rescored, pres))
        return out

    def _presence(self, q, ranked, canonical, negatives, cfg: PresenceConfig, probes) -> list[Presence]:
        """Presence of each unit query [n,D] from the first cfg.rows rows of its ranking (ranked again
        without the threshold where the threshold left fewer), with its probe's query and contrasts."""
        short = [j for j, r in enumerate(ranked) if len(r.rows) < min(cfg.rows, self.num_embedded)]
        best = [r.rows[: cfg.rows] for r in ranked]
        if short:
            again = self.index.rank_many(q[short], cfg.rows, 0.0, canonical)
            for j, r in zip(short, again, strict=True):
                best[j] = r.rows
        out = []
        for j, rows in enumerate(best):
            if len(rows) == 0:
                out.append(NO_GAUSSIANS)
                continue
            pq, con = self.probe_vectors(q[j], None if probes is None else probes[j])
            dots = self.index.exact_dots(rows, torch.cat([pq[None], negatives, con]))  # [T,1+V+S] float64
            qn = negatives.double() @ pq.double()
            V = len(negatives)
            out.append(presence(dots[:, 0], dots[:, 1 : 1 + V], qn, cfg, dots[:, 1 + V :]))
        return out

    def probe_vectors(self, q: torch.Tensor, probe: Probe | None) -> tuple[torch.Tensor, torch.Tensor]:
        """The unit presence query [D] and contrasts [S,D] for unit query q [D] and its probe: the query
        itself and no contrasts when the probe has none (or there is no probe)."""
        if probe is None or not len(probe.contrasts):
            return q, q.new_zeros((0, len(q)))
        return self.unit(probe.query[None], "presence probe")[0], self.unit(
            probe.contrasts, "colour contrasts"
        )

    def instance_inputs(self, index: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """Means [K,3] and opacities [K] float64 of the Gaussians at scene indices [K], as instance grouping
        reads them: opacities from those rows' logits in float64 (a float32 sigmoid over the whole scene
        rounds some rows differently from one over a shard)."""
        g = self.gaussians
        means = g.means[index].detach().cpu().double().numpy()
        return means, torch.sigmoid(g.opacity_logits[index].detach().cpu().double()).numpy()

    def gaussian_columns(self, index: torch.Tensor, names) -> dict[str, np.ndarray]:
        """Attributes of the Gaussians at scene indices [K], float32, for each name asked (a subset of
        GAUSSIAN_COLUMNS): mean [K,3]; opacity [K]; scale [K,3] (activated); rotation [K,4] unit wxyz
        (identity for a zero quaternion); color [K,3] (degree-0 SH, clamped to [0,1])."""
        bad = sorted(set(names) - set(GAUSSIAN_COLUMNS))
        if bad:
            raise ValidationError("fields", f"unknown Gaussian columns {bad}; choose from {GAUSSIAN_COLUMNS}")
        g, out = self.gaussians, {}
        f32 = lambda t: t.float().cpu().numpy()  # noqa: E731
        for name in names:
            if name == "mean":
                out[name] = f32(g.means[index])
            # Activated from the rows asked only, in float64 rounded to float32: float32 sigmoid and exp
            # take a vector path for most elements and a scalar one for the rest, so a Gaussian's value
            # would depend on where it sits (shards would not match the whole scene bit for bit).
            elif name == "opacity":
                out[name] = f32(torch.sigmoid(g.opacity_logits[index].double()))
            elif name == "scale":
                out[name] = f32(torch.exp(g.log_scales[index].double()))
            elif name == "rotation":
                q = g.quats[index].double()
                n = q.norm(dim=1, keepdim=True)
                unit = torch.tensor([1.0, 0, 0, 0], dtype=q.dtype, device=q.device)
                out[name] = f32(torch.where(n > 0, q / n.clamp_min(1e-300), unit))
            else:
                out[name] = f32((0.5 + SH_C0 * g.sh[index, 0]).clamp(0, 1))
        return out

    @torch.no_grad()
    def warm_up(self) -> float:
        """Run a tiny text query and a 16x16 relevancy and colour render, so that the kernels a first
        request needs are compiled (numba JIT) and touched before it comes; returns the seconds taken."""

        t0 = time.perf_counter()
        q = torch.zeros(self.dim)
        q[0] = 1.0
        self.text_query(q, 1)
        lo, hi = self.bounds[:3], self.bounds[3:]
        eye = (lo + hi) / 2 - np.array([0.0, 0.0, 2.0 * max(float(np.max(hi - lo)), 1e-3)])
        V = torch.eye(4, dtype=torch.float64)
        V[:3, 3] = -torch.from_numpy(eye)
        K = torch.tensor([[16.0, 0, 8], [0, 16.0, 8], [0, 0, 1]], dtype=torch.float64)
        render_pose(self, Camera(K, V, 16, 16), q, ("relevancy", "rgb"))
        with self._cache_lock:
            self._chan_cache.clear()  # the warm-up query is nobody's
        return time.perf_counter() - t0

    def _eps_for(self, cfg: InstanceConfig) -> float:
        if cfg.eps_fraction == InstanceConfig().eps_fraction:
            return self._eps
        return default_eps(self.gaussians.means.detach().cpu().double().numpy(), cfg.eps_fraction)

    def channels(self, vectors: torch.Tensor, rows: torch.Tensor | None = None) -> torch.Tensor:
        """[M,n] f.v per embedded Gaussian for unit vectors [n,D], float32: the exact float32 table's dots,
        or on the compact path the stored embeddings' float64 dots rounded to float32 for ``rows`` ([M]
        bool; None: every row) and 0 elsewhere. The compact state's int8 scores never reach an image or a
        label: they choose candidates for text queries only."""
        if self.index.exact:
            return self.index.dots(vectors)
        out = torch.zeros(self.num_embedded, len(vectors))
        idx = np.arange(self.num_embedded) if rows is None else np.flatnonzero(rows.numpy())
        if len(idx):
            out[torch.from_numpy(idx)] = self._exact_rows(vectors, idx)
        return out

    def _exact_rows(self, vectors: torch.Tensor, rows: np.ndarray) -> torch.Tensor:
        """[k,n] float32 f.v for sorted rows [k]: the stored embeddings' float64 dots, rounded once."""
        return self.index.exact_dots(torch.from_numpy(rows), vectors).float()

    def relevancy_channels(
        self, query: torch.Tensor, canonical: torch.Tensor | None = None, rows: torch.Tensor | None = None
    ) -> torch.Tensor:
        """[M,1+C] (f.q, f.c_n) per embedded Gaussian, the channels of a relevancy render.

        ``rows`` [M] bool: the Gaussians the render can touch (fmgs.render.visible; None: every row). On
        the compact path only those are guaranteed to hold their values (``channels``: exact dots of the
        stored embeddings; the stored canonical dots are exact already), others may hold 0: the compact
        scores may choose rows for text queries, they never colour an image, so a relevancy image does not
        depend on the scene's size or the device. Cached for the last few queries: a pose stream asks the
        same text for many poses, and then a frame scores only the rows no earlier frame touched.
        """
        vecs = self.unit(query[None])
        canon = None if canonical is None else self.unit(canonical, "canonical embeddings")
        key = vecs.numpy().tobytes() + (b"" if canon is None else canon.numpy().tobytes())
        scored_vecs = vecs if canon is None else torch.cat([vecs, canon])
        # Channels live on the index's device (the GPU with a CUDA engine): a cached query costs no copy.
        with self._cache_lock:
            entry = self._chan_cache.get(key)
            if entry is not None:
                self._chan_cache.move_to_end(key)
        if entry is None:
            entry = self._new_channels(scored_vecs, canon is None)
            with self._cache_lock:
                entry = self._chan_cache.setdefault(key, entry)  # a concurrent first render's, if any
                self._chan_cache.move_to_end(key)
                while len(self._chan_cache) > self.CHANNEL_CACHE:
                    self._chan_cache.popitem(last=False)
        if entry.scored is not None:
            with entry.lock:
                need = ~entry.scored if rows is None else rows.numpy() & ~entry.scored
                idx = np.flatnonzero(need)
                if len(idx):
                    entry.values[torch.from_numpy(idx), : len(scored_vecs)] = self._exact_rows(
                        scored_vecs, idx
                    )
                    entry.scored[idx] = True
        return entry.values

    def _new_channels(self, vecs: torch.Tensor, stored_canonical: bool) -> _Channels:
        """A query's channels: every row's exact dots on the exact path; on the compact path the stored
        canonical dots (when ``stored_canonical``) and zeros for the rows to score."""
        if self.index.exact:
            dots = self.channels(vecs)
            values = torch.cat([dots, self.index.canonical], 1) if stored_canonical else dots
            return _Channels(values, None)
        values = torch.zeros(
            self.num_embedded, len(vecs) + (self.index.canonical.shape[1] if stored_canonical else 0)
        )
        if stored_canonical:
            values[:, len(vecs) :] = self.index.canonical
        return _Channels(values, np.zeros(self.num_embedded, bool))
