"""Text queries on a sharded scene: each shard ranks its own rows, the merge is the exact top K.

A shard answers with its best rows under the served ranking (margin descending), their float64
margins, and what the merge needs to finish the answer as the unsharded engine would (presence dots of
its best rows, the means and opacities that instance grouping reads, the asked-for Gaussian columns).
Margins are computed per row from stored bits in a fixed order (fmgs.query.index), so a row scores the
same in its shard as in the source, and ordering the union by (margin descending, source row
ascending) gives the source's answer bit for bit: the K best overall are among the K best of each shard.

``shard_text`` runs where the shard is held (in-process, or in a Ray replica); ``merge_text`` wherever
the request arrived. Both are plain data in, plain data out (numpy), so the parts can travel.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from fmgs.errors import ValidationError
from fmgs.query.certify import order_rows
from fmgs.query.engine import NO_GAUSSIANS, PRESENCE, EngineConfig, SceneEngine, TextAnswer
from fmgs.query.instances import InstanceConfig, group_instances
from fmgs.query.pose import PoseRender, relevancy_layer, score_image
from fmgs.query.presence import Presence, PresenceConfig, Probe, presence
from fmgs.scene.shards import ShardManifest, front_to_back, read_shard_ids, shard_folders
from fmgs.vecmath import safe_normalize


class ShardPart(NamedTuple):
    """One shard's best rows for one text (numpy, source indices)."""

    rows: np.ndarray
    """[k] int64 source rows (into the source's embedded Gaussians), best first."""
    index: np.ndarray
    """[k] int64 source Gaussian indices."""
    margin: np.ndarray
    """[k] float64 exact margins."""
    relevancy: np.ndarray
    """[k] float32."""
    similarity: np.ndarray
    """[k] float32."""
    rescored: int
    presence_dots: np.ndarray | None
    """[min(k,T),1+V+S] float64 f.[probe query, negatives, contrasts] of the first rows (None without
    negatives)."""
    means: np.ndarray | None
    """[k,3] float64 (None unless instances are asked for)."""
    opacity: np.ndarray | None
    """[k] float64 (None unless instances are asked for)."""
    columns: dict[str, np.ndarray]
    """Asked-for Gaussian columns (SceneEngine.gaussian_columns), [k,...] float32."""


@dataclass(frozen=True)
class ShardQuery:
    """What every shard is asked (the same for all of them)."""

    queries: np.ndarray
    """[n,D] float32 query embeddings (normalised by each shard as the engine does)."""
    top_k: int
    threshold: float = 0.0
    canonical: np.ndarray | None = None
    """[C,D] float32 replacement canonical embeddings, or None."""
    negatives: np.ndarray | None = None
    """[V,D] float32 presence negatives, or None."""
    probes: tuple[tuple[np.ndarray, np.ndarray], ...] | None = None
    """Per text, its presence probe's query [D] and colour contrasts [S,D] float32
    (fmgs.query.presence.Probe), or None: each text is its own probe."""
    instances: bool = False
    columns: tuple[str, ...] = ()
    presence_rows: int = PRESENCE.rows


def shard_probes(probes: Sequence[Probe] | None) -> tuple[tuple[np.ndarray, np.ndarray], ...] | None:
    """ShardQuery.probes from fmgs.query.presence.probes."""
    if probes is None:
        return None
    f32 = lambda t: t.detach().float().cpu().numpy()  # noqa: E731
    return tuple((f32(p.query), f32(p.contrasts)) for p in probes)


def _t(a: np.ndarray | None) -> torch.Tensor | None:
    return None if a is None else torch.from_numpy(np.ascontiguousarray(a, np.float32))


@torch.no_grad()
def shard_text(engine: SceneEngine, rows_map: torch.Tensor, gauss_map: torch.Tensor, sq: ShardQuery):
    """This shard's parts for every query ([n] ShardPart). rows_map [m] / gauss_map [n_g] int64: source
    row of each local row and source index of each local Gaussian (fmgs.scene.shards.read_shard_ids)."""
    q = engine.unit(_t(sq.queries))
    c = None if sq.canonical is None else engine.unit(_t(sq.canonical), "canonical embeddings")
    neg = None if sq.negatives is None else engine.unit(_t(sq.negatives), "negative embeddings")
    # Without a threshold cut, presence reads the unthresholded best rows: rank that many, cut later.
    k = sq.top_k if neg is None else max(sq.top_k, sq.presence_rows)
    thr = sq.threshold if neg is None else 0.0
    ranked = engine.index.rank_many(q, k, thr, c)
    out = []
    for j, r in enumerate(ranked):
        local = engine.selected[r.rows]
        pd = None
        if neg is not None:
            first = r.rows[: sq.presence_rows]
            probe = None if sq.probes is None else Probe(_t(sq.probes[j][0]), _t(sq.probes[j][1]), ())
            pq, con = engine.probe_vectors(q[j], probe)
            pd = engine.index.exact_dots(first, torch.cat([pq[None], neg, con])).cpu().numpy()
        means = opac = None
        if sq.instances:
            means, opac = engine.instance_inputs(local)
        out.append(
            ShardPart(
                rows_map[r.rows].numpy(),
                gauss_map[local].numpy(),
                r.margin.cpu().numpy(),
                r.relevancy.numpy(),
                r.similarity.numpy(),
                int(r.rescored),
                pd,
                means,
                opac,
                engine.gaussian_columns(local, sq.columns),
            )
        )
    return out


def merge_text(
    parts: Sequence[ShardPart],
    sq: ShardQuery,
    j: int,
    instances: InstanceConfig | None,
    means_box: Sequence[float],
    presence_cfg: PresenceConfig = PRESENCE,
) -> TextAnswer:
    """Text j's answer from every shard's part for it: the exact top K of the union, presence from the
    best presence_cfg.rows rows, instances grouped after the merge."""
    rows = np.concatenate([p.rows for p in parts])
    margin = torch.from_numpy(np.concatenate([p.margin for p in parts]))
    order = order_rows(margin, torch.from_numpy(rows)).numpy()
    pres = None if sq.negatives is None else _merged_presence(parts, order, j, sq, presence_cfg)
    rel_all = np.concatenate([p.relevancy for p in parts])
    keep = order[: sq.top_k]
    keep = keep[rel_all[keep] >= sq.threshold]  # a prefix: relevancy falls with the margin

    def cat(name: str) -> np.ndarray:
        return np.concatenate([getattr(p, name) for p in parts])[keep]

    rel = rel_all[keep]
    cols = {name: np.concatenate([p.columns[name] for p in parts])[keep] for name in sq.columns}
    inst, ids = [], None
    if instances is not None:
        box = np.asarray(means_box, np.float64)
        eps = instances.eps or max(float(np.linalg.norm(box[3:] - box[:3]) * instances.eps_fraction), 1e-9)
        inst, ids = group_instances(cat("means"), rel, cat("opacity"), instances, eps)
    return TextAnswer(
        torch.from_numpy(cat("index")),
        torch.from_numpy(rel),
        torch.from_numpy(cat("similarity")),
        inst,
        ids,
        sum(p.rescored for p in parts),
        pres,
        cols,
    )


def _merged_presence(parts, order, j: int, sq: ShardQuery, cfg: PresenceConfig) -> Presence:
    dots = [p.presence_dots for p in parts]
    have = np.concatenate([np.arange(len(p.rows)) < len(d) for p, d in zip(parts, dots, strict=True)])
    first = order[: cfg.rows]
    if len(first) == 0:
        return NO_GAUSSIANS
    if not have[first].all():  # cannot happen: the best T overall are among each shard's best T
        raise RuntimeError("a shard left out presence dots of a row among the best")
    # Position of each row's dots in the concatenation of the shards' dot blocks.
    starts = np.cumsum([0] + [len(p.rows) for p in parts[:-1]])
    dstarts = np.cumsum([0] + [len(d) for d in dots[:-1]])
    shard = np.searchsorted(starts, first, side="right") - 1
    pos = dstarts[shard] + (first - starts[shard])
    d = torch.from_numpy(np.concatenate(dots)[pos])
    coloured = sq.probes is not None and len(sq.probes[j][1])
    query = sq.probes[j][0] if coloured else sq.queries[j]
    q = safe_normalize(torch.from_numpy(np.asarray(query, np.float32))[None].float())[0]
    neg = safe_normalize(torch.from_numpy(np.asarray(sq.negatives, np.float32)).float())
    qn = neg.double() @ q.double()
    V = len(neg)
    return presence(d[:, 0], d[:, 1 : 1 + V], qn, cfg, d[:, 1 + V :])


class ShardedSceneEngine:
    """SceneEngine's twin for a sharded scene held in one process (every shard an engine): the exact twin
    of serving the shards on many replicas, and what tests compare against the unsharded engine."""

    def __init__(self, folder: str | Path, cfg: EngineConfig | None = None) -> None:
        cfg = cfg or EngineConfig()
        self.folder = Path(folder)
        self.manifest = ShardManifest.read(self.folder)
        self.engines, self.maps = [], []
        for info, path in zip(self.manifest.shards, shard_folders(self.folder), strict=True):
            e = SceneEngine.open(path, cfg)
            self.engines.append(e)
            self.maps.append(read_shard_ids(path, info.num_gaussians, info.num_selected))

    @torch.no_grad()
    def render_pose(self, camera, query, outputs=("relevancy",), canonical=None):
        """As fmgs.query.pose.render_pose for POSE_OUTPUTS: the shards' layers composited."""

        bad = [o for o in outputs if o not in POSE_OUTPUTS]
        if bad or not outputs:
            raise ValidationError("outputs", f"a sharded scene renders {POSE_OUTPUTS}, got {list(outputs)}")
        q = query if "relevancy" in outputs else None
        order = render_order(self.manifest, camera)
        return composite([shard_layer(self.engines[i], camera, q, canonical) for i in order], outputs)

    def text_query_many(
        self,
        queries: torch.Tensor,
        top_k: int,
        threshold: float = 0.0,
        canonical: torch.Tensor | None = None,
        instances: InstanceConfig | None = None,
        negatives: torch.Tensor | None = None,
        columns: tuple[str, ...] = (),
        probes: Sequence[Probe] | None = None,
        presence_cfg: PresenceConfig = PRESENCE,
    ) -> list[TextAnswer]:
        """As SceneEngine.text_query_many, the shards scored one after another here."""
        np32 = lambda t: None if t is None else t.detach().float().cpu().numpy()  # noqa: E731
        sq = ShardQuery(
            np32(queries), int(top_k), float(threshold), np32(canonical), np32(negatives),
            shard_probes(probes), instances is not None, tuple(columns), presence_cfg.rows,
        )  # fmt: skip
        per_shard = [
            shard_text(e, rows, gi, sq) for e, (gi, rows) in zip(self.engines, self.maps, strict=True)
        ]
        return [
            merge_text([p[j] for p in per_shard], sq, j, instances, self.manifest.means_box, presence_cfg)
            for j in range(len(sq.queries))
        ]


# ---------------------------------------------------------------------- pose queries

POSE_OUTPUTS = ("relevancy", "alpha")
"""What a sharded scene renders (colour and depth need every Gaussian's colour pass: not yet)."""


class ShardLayer(NamedTuple):
    """One shard's partial relevancy render: its embedded Gaussians alone, blended front to back."""

    channels: np.ndarray
    """[H,W,1+C] float32 blended (f.q, f.c_n) of the shard's Gaussians (premultiplied by their alpha)."""
    alpha: np.ndarray
    """[H,W] float32 accumulated opacity of the shard's Gaussians."""


@torch.no_grad()
def shard_layer(engine: SceneEngine, camera, query: torch.Tensor | None, canonical=None, between=None):
    """This shard's layer for a relevancy (or alpha-only, query None) render of ``camera``."""

    out = relevancy_layer(engine, camera, query, canonical, between)
    return ShardLayer(out.image.float().cpu().numpy(), out.alpha.float().cpu().numpy())


def composite(layers: Sequence[ShardLayer], outputs: tuple[str, ...]):
    """The PoseRender of layers given front to back: C = sum_i T_i C_i, T_i = prod_{j<i} (1 - A_j).

    Exact when every pixel's Gaussians of a nearer cell lie in front of a farther cell's; Gaussians
    straddling a split plane and the rasteriser's early stop make the difference measured in
    benchmarks/results/CLUSTER.md against the unsharded render.
    """

    img = np.zeros_like(layers[0].channels, dtype=np.float64)
    trans = np.ones_like(layers[0].alpha, dtype=np.float64)
    for layer in layers:
        img += trans[..., None] * layer.channels
        trans *= 1.0 - layer.alpha
    img_t = torch.from_numpy(img.astype(np.float32))
    alpha = torch.from_numpy((1.0 - trans).astype(np.float32))
    rel = arg = None
    if "relevancy" in outputs:
        rel, arg = score_image(img_t)
    return PoseRender(rel, None, None, alpha if "alpha" in outputs else None, arg)


def render_order(manifest: ShardManifest, camera) -> list[int]:
    """Shard indices front to back for ``camera`` (ValidationError for a manifest without its tree)."""

    if manifest.tree is None:
        raise ValidationError(
            "shards.json", "has no k-d tree (written before pose queries on shards); reshard"
        )
    V = camera.viewmat.double()
    eye = -(V[:3, :3].T @ V[:3, 3])
    return front_to_back(manifest.tree, eye.tolist())
