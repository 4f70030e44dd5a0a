"""What a Ray scene replica does, without Ray: run the service's handlers on forwarded requests.

The ingress forwards a call as (method, serialized request); the replica runs the same ``FmgsService``
handler that ``fmgs serve`` runs, with a ``ForwardedContext`` in place of grpc's, and returns the
serialized answer messages, ending with a ``Status`` when the handler failed. Errors therefore get the
codes and messages of the README's table, whichever process answers.

Sharded scenes (fmgs.scene.shards) are answered here too: ``plan_sharded_text`` validates and embeds a
TextQuery, the caller scatters the ShardQuery to the replicas holding the shards (``shard_text``), and
``finish_sharded_text`` merges their parts into the same chunks an unsharded scene gives.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import grpc

from fmgs.errors import FmgsError
from fmgs.scene.manifest import Manifest
from fmgs.scene.shards import SHARDS_FILE, ShardManifest, is_sharded, read_shard_ids
from fmgs_server import convert, responses
from fmgs_server.calls import status_of
from fmgs_server.config import ServerConfig
from fmgs_server.errors import FailedPrecondition, NotFound
from fmgs_server.server import make_service
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb

REQUEST_TYPES = {m.name: m.input_type.name for m in pb.DESCRIPTOR.services_by_name["Fmgs"].methods}
"""RPC name -> request message name."""


class Status(NamedTuple):
    """How a forwarded call ended when it did not end OK."""

    code: str
    """grpc.StatusCode name."""
    details: str


class Aborted(Exception):
    def __init__(self, code: grpc.StatusCode, details: str) -> None:
        super().__init__(details)
        self.code, self.details = code, details


class ForwardedContext:
    """The part of grpc.ServicerContext the service uses, for a call forwarded by the ingress.

    The Ray proxy does not forward the client's deadline; ``deadline_s`` (monotonic seconds) is the
    server-side cap when one is configured. ``cancel()`` marks the call gone (the ingress saw the client
    leave), so long work stops at its next check.
    """

    def __init__(self, deadline_s: float | None = None) -> None:
        self.deadline_s = deadline_s
        self._gone = threading.Event()

    def cancel(self) -> None:
        self._gone.set()

    def is_active(self) -> bool:
        return not self._gone.is_set() and (self.deadline_s is None or time.monotonic() < self.deadline_s)

    def time_remaining(self) -> float | None:
        return None if self.deadline_s is None else self.deadline_s - time.monotonic()

    def abort(self, code: grpc.StatusCode, details: str):
        raise Aborted(code, details)


def _status(e: BaseException) -> Status:
    if isinstance(e, Aborted):
        return Status(e.code.name, e.details)
    code, text = status_of(e)
    return Status(code.name, text)


@dataclass
class ShardedPlan:
    """A validated, embedded text query on a sharded scene, ready to scatter."""

    scene: str
    shards: tuple[str, ...]
    """Shard folders (each a multiplexed id ``scene/folder``)."""
    query: object
    """fmgs.query.sharded.ShardQuery."""
    texts: list[str]
    fields: set[int]
    instances: object
    negatives: tuple[str, ...]
    means_box: tuple[float, ...]
    t0: float


class HostCore:
    """A replica's scenes and service (fmgs_server.server.make_service) and its forwarded calls."""

    def __init__(self, cfg: ServerConfig, encoder_factory=None) -> None:
        self.cfg = cfg
        self.service = make_service(cfg, encoder_factory)
        self._shard_repos: dict[str, object] = {}
        self._ids: dict[tuple[str, str], tuple] = {}
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ whole scenes

    def unary(self, method: str, request: bytes, ctx: ForwardedContext | None = None) -> bytes | Status:
        """Run unary RPC ``method`` on a serialized request: the serialized answer, or how it failed."""
        ctx = ctx or ForwardedContext()
        try:
            req = getattr(pb, REQUEST_TYPES[method]).FromString(request)
            scene = getattr(req, "scene", "")
            if scene and self.is_sharded(scene):
                if method == "GetScene":
                    return self.sharded_info(scene).SerializeToString()
                return not_sharded(method, scene)
            answer = getattr(self.service, method)(req, ctx)
            if method == "ListScenes":
                answer.scenes.extend(self.sharded_info(n) for n in self.list_sharded())
                answer.scenes.sort(key=lambda i: i.name)
            return answer.SerializeToString()
        except Exception as e:
            return _status(e)

    def stream(
        self, method: str, request: bytes, ctx: ForwardedContext | None = None
    ) -> list[bytes | Status]:
        """Run server-streaming RPC ``method``: its messages, ending with a Status if it failed. The
        answer is collected whole (its size is bounded by the request limits and the work budget)."""
        ctx = ctx or ForwardedContext()
        out: list[bytes | Status] = []
        try:
            req = getattr(pb, REQUEST_TYPES[method]).FromString(request)
            scene = getattr(req, "scene", "")
            if scene and self.is_sharded(scene):
                return [not_sharded(method, scene)]
            for msg in getattr(self.service, method)(req, ctx):
                out.append(msg.SerializeToString())
        except Exception as e:
            out.append(_status(e))
        return out

    def unload(self, scene: str) -> None:
        """Drop a scene this replica holds (Ray's multiplexer evicted it)."""
        if "/" in scene:
            name, shard = scene.split("/", 1)
            repo = self._shard_repos.get(name)
            if repo is not None:
                try:
                    repo.unload(shard)
                except FmgsError:
                    pass
            return
        try:
            self.service.repo.unload(scene)
        except Exception:  # not found: nothing to drop
            pass

    # ------------------------------------------------------------------ sharded scenes

    def is_sharded(self, scene: str) -> bool:
        from fmgs.scene.package import check_scene_name

        try:
            check_scene_name(scene)
        except FmgsError:
            return False
        return is_sharded(self.cfg.models / scene)

    def _shard_engine(self, scene: str, folder: str):
        from fmgs.query.engine import EngineConfig, SceneEngine
        from fmgs_server.repository import SceneRepository

        with self._lock:
            repo = self._shard_repos.get(scene)
            if repo is None:
                ecfg = EngineConfig(self.cfg.index, device=self.cfg.device)
                repo = SceneRepository(
                    self.cfg.models / scene,
                    lambda p: SceneEngine.open(p, ecfg),
                    self.cfg.memory_budget_bytes,
                    self.cfg.reload_check_s,
                )
                self._shard_repos[scene] = repo
        engine = repo.get(folder)
        key = (scene, folder)
        with self._lock:
            ids = self._ids.get(key)
            if ids is None or ids[0] is not engine:
                path = self.cfg.models / scene / folder
                ids = (engine, *read_shard_ids(path, engine.num_gaussians, engine.num_embedded))
                self._ids[key] = ids
        return ids

    def shard_text(self, scene: str, folder: str, sq) -> list | Status:
        """This replica's parts of a sharded text query (fmgs.query.sharded.shard_text) for shard
        ``folder`` of ``scene``, or how it failed."""
        from fmgs.query.sharded import shard_text

        try:
            engine, gi, rows = self._shard_engine(scene, folder)
            with self.service.slots.compute(ForwardedContext()):
                return shard_text(engine, rows, gi, sq)
        except Exception as e:
            return _status(e)

    def plan_sharded_text(self, scene: str, request: bytes) -> ShardedPlan | Status:
        """Validate and embed a TextQuery on sharded ``scene``."""
        import numpy as np

        from fmgs.query.presence import negative_names
        from fmgs.query.sharded import ShardQuery

        try:
            req = pb.TextQueryRequest.FromString(request)
            cfg, svc = self.cfg, self.service
            sm = ShardManifest.read(cfg.models / scene)
            if req.HasField("embeddings") or req.canonical_phrases:
                raise FailedPrecondition(
                    f"scene {scene!r} is sharded: its text queries take texts and the scene's canonical "
                    "phrases (embeddings and canonical_phrases are not supported on sharded scenes yet)"
                )
            values = convert.texts(req.texts, cfg)
            k = convert.top_k(req.top_k, cfg)
            thr = convert.threshold(req.threshold)
            fields = set(req.fields)
            inst = convert.instance_config(req.instances) if req.instances.enabled else None
            first = Manifest.read(cfg.models / scene / sm.shards[0].folder)
            names = tuple(negative_names(first.label_names))
            t0 = time.perf_counter()
            q = svc.encoders.embed(sm.encoder_id, values)
            negs = svc.encoders.negatives(sm.encoder_id, names)
            cols = tuple(n for f, n in responses.COLUMNS.items() if f in fields)
            sq = ShardQuery(
                q.float().numpy(), k, thr, None, negs.float().numpy().astype(np.float32),
                inst is not None, cols,
            )  # fmt: skip
            shards = tuple(s.folder for s in sm.shards)
            return ShardedPlan(scene, shards, sq, values, fields, inst, names, sm.means_box, t0)
        except Exception as e:
            return _status(e)

    def finish_sharded_text(self, plan: ShardedPlan, parts: list) -> list[bytes | Status]:
        """Merge the shards' parts (parts[s][j]: shard s, text j) into the answer's chunks."""
        from fmgs.query.sharded import merge_text

        out: list[bytes | Status] = []
        try:
            for p in parts:
                if isinstance(p, Status):
                    return [p]
            sq = plan.query
            n = len(plan.texts)
            answers = [
                merge_text([p[j] for p in parts], sq, sq.queries[j], plan.instances, plan.means_box)
                for j in range(n)
            ]
            ms = (time.perf_counter() - plan.t0) * 1e3 / max(1, n)
            for i, (text, a) in enumerate(zip(plan.texts, answers, strict=True)):
                chunks = responses.text_chunks(
                    None, i, text, a, plan.fields, ms, self.cfg.chunk_bytes, plan.negatives
                )
                out.extend(c.SerializeToString() for c in chunks)
        except Exception as e:
            out.append(_status(e))
        return out

    def sharded_info(self, scene: str) -> pb.SceneInfo:
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
        return info

    def list_sharded(self) -> list[str]:
        """Names of the sharded scenes in the repository."""
        root = self.cfg.models
        if not root.is_dir():
            return []
        return sorted(
            p.name for p in root.iterdir() if not p.name.startswith(".") and self.is_sharded(p.name)
        )


def _version(folder: Path) -> str:
    try:
        return str(int((folder / SHARDS_FILE).stat().st_mtime_ns))
    except OSError:
        return ""


def not_sharded(method: str, scene: str) -> Status:
    """The answer to an RPC that sharded scenes do not support (yet)."""
    e = FailedPrecondition(
        f"scene {scene!r} is sharded: {method} is not supported on sharded scenes (text queries are)"
    )
    return _status(e)


def missing(scene: str) -> Status:
    return _status(NotFound(f"scene {scene!r} not found in the model repository"))
