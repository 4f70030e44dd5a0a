"""Sharded scenes in the scene repository (fmgs.scene.shards): text queries and relevancy renders.

Each call is three steps, so the middle one can run anywhere: ``plan_*`` validates and embeds the request
where it arrived, ``shard_*`` computes one shard's part (fmgs.query.sharded) where the shard is held, and
``finish_*`` merges the parts into the same answer messages an unsharded scene gives. ``fmgs serve``
runs all three in its own process (``text_query``, ``render``); a Ray cluster scatters the middle step to
the replicas holding the shards (fmgs_server.cluster). Errors are raised as the service raises them
(fmgs_server.errors), so they reach the client with the codes of docs/serving.md either way.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from fmgs.errors import FmgsError
from fmgs.scene.manifest import Manifest
from fmgs.scene.shards import SHARDS_FILE, ShardManifest, is_sharded, read_shard_ids
from fmgs_server import convert, responses
from fmgs_server.config import ServerConfig
from fmgs_server.encoders import EncoderCache, TextModel, scene_text_model
from fmgs_server.errors import FailedPrecondition
from fmgs_server.slots import Slots
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb

SHARDED_METHODS = ("ListScenes", "GetScene", "TextQuery", "Render", "StreamRender")
"""RPCs that answer on sharded scenes; the others get FAILED_PRECONDITION naming the scene."""


@dataclass
class TextPlan:
    """A validated, embedded text query on a sharded scene, ready to scatter."""

    scene: str
    shards: tuple[str, ...]
    """Shard folders."""
    query: object
    """fmgs.query.sharded.ShardQuery."""
    texts: list[str]
    fields: set[int]
    instances: object
    rivals: tuple[tuple[str, ...], ...]
    """Per text, the names its presence rival is chosen from (negatives, then its colour contrasts)."""
    means_box: tuple[float, ...]
    t0: float


@dataclass
class RenderPlan:
    """A validated render of a sharded scene, ready to scatter: shards in front-to-back order."""

    scene: str
    shards: tuple[str, ...]
    camera: object
    query: object
    """[D] float32 text embedding (None for alpha only)."""
    canonical: object
    outputs: tuple[str, ...]
    encoding: int
    sequence: int
    t0: float


def sharded_scene(models: Path, scene: str) -> bool:
    """Whether ``scene`` names a sharded scene of repository ``models`` (a valid name with a shards.json)."""
    from fmgs.scene.package import check_scene_name

    try:
        check_scene_name(scene)
    except FmgsError:
        return False
    return is_sharded(models / scene)


def not_supported(method: str, scene: str) -> FailedPrecondition:
    return FailedPrecondition(
        f"scene {scene!r} is sharded: {method} is not supported on sharded scenes (text queries and "
        "relevancy renders are)"
    )


class ShardedSceneService:
    """The service's side for the repository's sharded scenes: lists them, holds their shards' engines,
    and answers text queries and renders on them with the service's text encoders and compute slots."""

    def __init__(self, cfg: ServerConfig, encoders: EncoderCache, slots: Slots) -> None:
        """``encoders`` and ``slots``: the service's own (fmgs_server.service.FmgsService), shared with
        its unsharded scenes."""
        self.cfg = cfg
        self.encoders = encoders
        """Embeds texts, presence names and canonical phrases with a scene's encoder."""
        self.slots = slots
        """Compute slots: a shard's part of a call holds one while it computes."""
        self._repos: dict[str, object] = {}
        self._ids: dict[tuple[str, str], tuple] = {}
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ listing

    def is_sharded(self, scene: str) -> bool:
        return sharded_scene(self.cfg.models, scene)

    def names(self) -> list[str]:
        root = self.cfg.models
        if not root.is_dir():
            return []
        names = (p.name for p in root.iterdir() if not p.name.startswith("."))
        return sorted(n for n in names if self.is_sharded(n))

    def info(self, scene: str) -> pb.SceneInfo:
        """A sharded scene as a SceneInfo (READY: its shards load where they are queried)."""
        try:
            sm = ShardManifest.read(self.cfg.models / scene)
            first = Manifest.read(self.cfg.models / scene / sm.shards[0].folder)
        except FmgsError as e:
            return pb.SceneInfo(name=scene, state=pb.SCENE_STATE_FAILED, reason=str(e))
        info = pb.SceneInfo(name=scene, state=pb.SCENE_STATE_READY, version=_version(self.cfg.models / scene))
        info.encoder_id, info.embedding_dim = sm.encoder_id, sm.dim
        info.num_gaussians, info.num_embedded = sm.num_gaussians, sm.num_selected
        info.sh_degree, info.has_field = first.sh_degree, first.field is not None
        info.canonical_phrases.extend(first.canonical)
        info.label_names.extend(first.label_names)
        info.frame_id = first.frame_id
        return info

    def text_model(self, scene: str, sm: ShardManifest, first: Manifest | None = None) -> TextModel:
        """The scene's text encoder at the revision its shards' manifests record (its first shard's)."""
        if first is None:
            first = Manifest.read(self.cfg.models / scene / sm.shards[0].folder)
        return scene_text_model(sm.encoder_id, first.extra, self.cfg.allow_newer_model, scene)

    # ------------------------------------------------------------------ shards held here

    def engine(self, scene: str, folder: str):
        """(engine, source Gaussian indices, source rows) of shard ``folder`` of ``scene``, loaded here."""
        from fmgs.query.engine import EngineConfig, SceneEngine
        from fmgs_server.repository import SceneRepository

        with self._lock:
            repo = self._repos.get(scene)
            if repo is None:
                ecfg = EngineConfig(self.cfg.index, backend=self.cfg.backend, device=self.cfg.device)
                repo = SceneRepository(
                    self.cfg.models / scene,
                    lambda p: SceneEngine.open(p, ecfg),
                    self.cfg.memory_budget_bytes,
                    self.cfg.reload_check_s,
                )
                self._repos[scene] = repo
        engine = repo.get(folder)
        key = (scene, folder)
        with self._lock:
            ids = self._ids.get(key)
            if ids is None or ids[0] is not engine:
                path = self.cfg.models / scene / folder
                ids = (engine, *read_shard_ids(path, engine.num_gaussians, engine.num_embedded))
                self._ids[key] = ids
        return ids

    def unload(self, scene: str, folder: str) -> None:
        repo = self._repos.get(scene)
        if repo is not None:
            try:
                repo.unload(folder)
            except FmgsError:
                pass

    def _slot(self, context):
        return self.slots.compute(context)

    # ------------------------------------------------------------------ text queries

    def plan_text(self, scene: str, req: pb.TextQueryRequest) -> TextPlan:
        import numpy as np

        from fmgs.query.presence import negative_names
        from fmgs.query.presence import probes as probe_texts
        from fmgs.query.sharded import ShardQuery, shard_probes

        cfg, encoders = self.cfg, self.encoders
        sm = ShardManifest.read(cfg.models / scene)
        if req.HasField("embeddings") or req.canonical_phrases:
            raise FailedPrecondition(
                f"scene {scene!r} is sharded: its text queries take texts and the scene's canonical "
                "phrases (embeddings and canonical_phrases are not supported on sharded scenes yet)"
            )
        values = convert.texts(req.texts, cfg)
        k = convert.top_k(req.top_k, cfg)
        thr = convert.threshold(req.threshold)
        fields = convert.fields(req.fields)
        inst = (
            convert.instance_config(req.instances, cfg.max_instance_pairs) if req.instances.enabled else None
        )
        first = Manifest.read(cfg.models / scene / sm.shards[0].folder)
        names = tuple(negative_names(first.label_names))
        model = self.text_model(scene, sm, first)
        t0 = time.perf_counter()
        q = encoders.embed(model, values)
        negs = encoders.negatives(model, names)
        probes = probe_texts(values, q, lambda ts: encoders.embed(model, ts))
        cols = tuple(n for f, n in responses.COLUMNS.items() if f in fields)
        sq = ShardQuery(
            q.float().numpy(), k, thr, None, negs.float().numpy().astype(np.float32), shard_probes(probes),
            inst is not None, cols,
        )  # fmt: skip
        shards = tuple(s.folder for s in sm.shards)
        rivals = tuple(names + p.names for p in probes)
        return TextPlan(scene, shards, sq, values, fields, inst, rivals, sm.means_box, t0)

    def shard_text(self, scene: str, folder: str, sq, context) -> list:
        from fmgs.query.sharded import shard_text

        engine, gi, rows = self.engine(scene, folder)
        with self._slot(context):
            return shard_text(engine, rows, gi, sq)

    def finish_text(self, plan: TextPlan, parts: list) -> Iterator[pb.TextQueryChunk]:
        from fmgs.query.sharded import merge_text

        sq, n = plan.query, len(plan.texts)
        pcfg = self.cfg.presence()
        answers = [
            merge_text([p[j] for p in parts], sq, j, plan.instances, plan.means_box, pcfg) for j in range(n)
        ]
        ms = (time.perf_counter() - plan.t0) * 1e3 / max(1, n)
        for i, (text, a) in enumerate(zip(plan.texts, answers, strict=True)):
            yield from responses.text_chunks(
                None, i, text, a, plan.fields, ms, self.cfg.chunk_bytes, plan.rivals[i]
            )

    def text_query(self, req: pb.TextQueryRequest, context, between: Callable[[], None]) -> Iterator:
        """The whole text query here, shard after shard (``fmgs serve``)."""
        plan = self.plan_text(req.scene, req)
        parts = []
        for f in plan.shards:
            between()
            parts.append(self.shard_text(req.scene, f, plan.query, context))
        yield from self.finish_text(plan, parts)

    # ------------------------------------------------------------------ relevancy renders

    def plan_render(self, scene: str, req: pb.RenderRequest) -> RenderPlan:
        from fmgs.query.sharded import POSE_OUTPUTS, render_order

        cfg, encoders = self.cfg, self.encoders
        sm = ShardManifest.read(cfg.models / scene)
        cam = convert.camera(req.camera, cfg, req.HasField("camera"))
        outputs = convert.outputs(req.outputs)
        encoding = convert.encoding(req.encoding)
        bad = [o for o in outputs if o not in POSE_OUTPUTS]
        if bad:
            raise FailedPrecondition(
                f"scene {scene!r} is sharded: it renders {', '.join(POSE_OUTPUTS)}, not {', '.join(bad)}"
            )
        t0 = time.perf_counter()
        q = canon = None
        model = self.text_model(scene, sm)
        if "relevancy" in outputs:
            values = convert.texts([req.text] if req.text else [], cfg, "text")
            q = encoders.embed(model, values)[0]
        phrases = convert.texts(req.canonical_phrases, cfg, "canonical_phrases", allow_empty=True)
        if phrases:
            canon = encoders.embed(model, phrases)
        order = tuple(sm.shards[i].folder for i in render_order(sm, cam))
        return RenderPlan(scene, order, cam, q, canon, outputs, encoding, req.sequence, t0)

    def shard_layer(self, scene: str, folder: str, plan: RenderPlan, context, between=None):
        from fmgs.query.sharded import shard_layer

        engine, _, _ = self.engine(scene, folder)
        with self._slot(context):
            return shard_layer(engine, plan.camera, plan.query, plan.canonical, between)

    def finish_render(self, plan: RenderPlan, layers: list) -> Iterator[pb.RenderChunk]:
        from fmgs.query.sharded import composite

        out = composite(layers, plan.outputs)
        ms = (time.perf_counter() - plan.t0) * 1e3
        yield from responses.render_chunks(
            plan.sequence, plan.camera, out, plan.encoding, ms, self.cfg.chunk_bytes
        )

    def render(self, req: pb.RenderRequest, context, between: Callable[[], None]) -> Iterator:
        """The whole render here, layer after layer (``fmgs serve``)."""
        plan = self.plan_render(req.scene, req)
        layers = [self.shard_layer(req.scene, f, plan, context, between) for f in plan.shards]
        yield from self.finish_render(plan, layers)


def _version(folder: Path) -> str:
    try:
        return str(int((folder / SHARDS_FILE).stat().st_mtime_ns))
    except OSError:
        return ""
