"""What a Ray scene replica does, without Ray: run the service's handlers on forwarded requests.

The ingress forwards a call as (method, serialized request); the replica runs the same ``FmgsService``
handler that ``fmgs serve`` runs, with a ``ForwardedContext`` in place of grpc's, and returns the
serialized answer messages, ending with a ``Status`` when the handler failed. Errors therefore get the
codes and messages of docs/serving.md's table, whichever process answers.

Sharded scenes (fmgs.scene.shards) are answered here too: ``plan_sharded_text`` validates and embeds a
TextQuery, the caller scatters the ShardQuery to the replicas holding the shards (``shard_text``), and
``finish_sharded_text`` merges their parts into the same chunks an unsharded scene gives.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import NamedTuple

import grpc

from fmgs.scene.manifest import Manifest
from fmgs_server.calls import status_of
from fmgs_server.config import ServerConfig
from fmgs_server.encoders import scene_text_model
from fmgs_server.errors import NotFound
from fmgs_server.server import make_service, warm_scene
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb

log = logging.getLogger("ray.serve")

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

    Ray Serve's proxy forwards neither the client's deadline nor its leaving, so a forwarded call is
    always active and has no deadline (the proxy's request_timeout_s caps it from outside).
    """

    def is_active(self) -> bool:
        return True

    def time_remaining(self) -> float | None:
        return None

    def abort(self, code: grpc.StatusCode, details: str):
        raise Aborted(code, details)


def _guarded(fn: Callable[[], object]):
    """fn()'s result, or the Status its exception maps to (docs/serving.md's error table)."""
    try:
        return fn()
    except Exception as e:
        return _status(e)


def _status(e: BaseException) -> Status:
    if isinstance(e, Aborted):
        return Status(e.code.name, e.details)
    code, text = status_of(e)
    return Status(code.name, text)


class HostCore:
    """A replica's scenes and service (fmgs_server.server.make_service) and its forwarded calls."""

    def __init__(self, cfg: ServerConfig, encoder_factory=None) -> None:
        self.cfg = cfg
        self.service = make_service(cfg, encoder_factory)

    def warm_up(self, warm=warm_scene) -> None:
        """What ``preload`` means on a replica (called before it takes traffic): the text encoder of every
        scene loaded, and the kernels compiled on the first scene that loads (``warm``), which is then
        unloaded again: Ray's multiplexer decides which scenes a replica holds, so each scene's first call
        on a replica still pays its load, but neither a compile nor an encoder's load."""
        compiled = False
        repo, encoders = self.service.repo, self.service.encoders
        for slot in repo.scan():
            try:
                if not compiled:
                    log.info("scene %s: warmed up in %.1f s", slot.name, warm(self.service, slot.name))
                    repo.unload(slot.name)
                    compiled = True
                else:
                    m = Manifest.read(repo.root / slot.name)
                    allow = self.service.cfg.allow_newer_model
                    encoders.encoder(scene_text_model(m.encoder_id, m.extra, allow, slot.name))
            except Exception as e:  # the scene's calls report it; the others are warm
                log.warning("scene %s: warm-up failed: %s", slot.name, e)

    # ------------------------------------------------------------------ whole scenes

    def unary(self, method: str, request: bytes) -> bytes | Status:
        """Run unary RPC ``method`` on a serialized request: the serialized answer, or how it failed."""

        def run() -> bytes:
            req = getattr(pb, REQUEST_TYPES[method]).FromString(request)
            return getattr(self.service, method)(req, ForwardedContext()).SerializeToString()

        return _guarded(run)

    def stream(self, method: str, request: bytes) -> list[bytes | Status]:
        """Run server-streaming RPC ``method``: its messages, ending with a Status if it failed. The
        answer is collected whole (its size is bounded by the request limits and the work budget)."""
        out: list[bytes | Status] = []
        try:
            req = getattr(pb, REQUEST_TYPES[method]).FromString(request)
            for msg in getattr(self.service, method)(req, ForwardedContext()):
                out.append(msg.SerializeToString())
        except Exception as e:
            out.append(_status(e))
        return out

    def unload(self, scene: str) -> None:
        """Drop a scene this replica holds (Ray's multiplexer evicted it)."""
        if "/" in scene:
            self.service.sharded.unload(*scene.split("/", 1))
            return
        try:
            self.service.repo.unload(scene)
        except Exception:  # not found: nothing to drop
            pass

    # ------------------------------------------------------------------ sharded scenes (scattered)

    def plan_sharded_text(self, scene: str, request: bytes):
        """Validate and embed a TextQuery on sharded ``scene`` (fmgs_server.sharded.TextPlan)."""
        sharded = self.service.sharded
        return _guarded(lambda: sharded.plan_text(scene, pb.TextQueryRequest.FromString(request)))

    def shard_text(self, scene: str, folder: str, sq) -> list | Status:
        """This replica's parts of a sharded text query for shard ``folder`` of ``scene``."""
        return _guarded(lambda: self.service.sharded.shard_text(scene, folder, sq, ForwardedContext()))

    def finish_sharded_text(self, plan, parts: list) -> list[bytes | Status]:
        """Merge the shards' parts (parts[s][j]: shard s, text j) into the answer's chunks."""
        return self._finish(lambda: self.service.sharded.finish_text(plan, parts), parts)

    def plan_sharded_render(self, scene: str, request: bytes):
        """Validate a RenderRequest on sharded ``scene``, embed its text, order the shards for its camera."""
        sharded = self.service.sharded
        return _guarded(lambda: sharded.plan_render(scene, pb.RenderRequest.FromString(request)))

    def shard_layer(self, scene: str, folder: str, plan):
        """This replica's layer of a sharded render, or how it failed."""
        return _guarded(lambda: self.service.sharded.shard_layer(scene, folder, plan, ForwardedContext()))

    def finish_sharded_render(self, plan, layers: list) -> list[bytes | Status]:
        """Composite the layers (front to back, as planned) into the render's chunks."""
        return self._finish(lambda: self.service.sharded.finish_render(plan, layers), layers)

    @staticmethod
    def _finish(chunks, parts: list) -> list[bytes | Status]:
        for p in parts:
            if isinstance(p, Status):
                return [p]
        out = _guarded(lambda: [c.SerializeToString() for c in chunks()])
        return [out] if isinstance(out, Status) else out


def missing(scene: str) -> Status:
    return _status(NotFound(f"scene {scene!r} not found in the model repository"))
