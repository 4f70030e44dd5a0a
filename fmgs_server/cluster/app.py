"""The ``fmgs.v1.Fmgs`` service as a Ray Serve application: an ingress behind Serve's gRPC proxy, and
scene replicas multiplexed by scene name.

- ``FmgsIngress`` has one method per RPC (Serve's proxy calls the method named like the RPC), plus
  ``Check``/``Watch`` for grpc.health.v1. It checks bearer tokens (fmgs_server.auth rules) and request
  sizes, forwards each call to the scene replica that holds the scene (``multiplexed_model_id`` = the
  scene name; a shard is ``scene/shard-NNN``), and turns a forwarded ``Status`` into the call's code.
  Text queries on sharded scenes are planned on the scene's replica, scattered to the shards' replicas
  at once, and merged there (fmgs_server.cluster.host).
- ``SceneHost`` replicas each hold a ``HostCore``: the same service ``fmgs serve`` runs, on the shared
  scene repository path. Scenes load on first use; Ray's multiplexer routes a scene's requests to the
  replicas that hold it and evicts least recently used scenes beyond ``scenes_per_replica``.

Answers pass through the ingress as serialized bytes (``Raw``): no second parse.
"""

from __future__ import annotations

import asyncio
import logging

import grpc
from grpc_health.v1 import health_pb2
from ray import serve

from fmgs_server.auth import TokenAuth, bearer_token, read_tokens
from fmgs_server.cluster.config import ClusterConfig
from fmgs_server.cluster.faults import failure_status, retryable
from fmgs_server.cluster.host import HostCore, Status, missing
from fmgs_server.config import ServerConfig
from fmgs_server.sharded import sharded_scene
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb

log = logging.getLogger("ray.serve")
"""Serve's logger: its lines land in the replica's own log (Serve configures no other logger there)."""

SERVICE = "fmgs.v1.Fmgs"
SERVICER_FUNCTIONS = [
    "fmgs_wire.proto.fmgs.v1.fmgs_pb2_grpc.add_FmgsServicer_to_server",
    "grpc_health.v1.health_pb2_grpc.add_HealthServicer_to_server",
]
"""What Serve's gRPC proxy registers (import paths; the proxy imports them on every node)."""
REPLICA_KEY = "fmgs-replica"
"""Trailing metadata naming the scene replica that answered (Ray only; clients may ignore it)."""
RESPONSE_TYPES = {m.name: m.output_type.name for m in pb.DESCRIPTOR.services_by_name["Fmgs"].methods}


class CallFailed(Exception):
    """Ends a streaming call whose code is already set on its context (Serve's proxy applies a code set
    by a stream only with a message or an exception)."""


RETRY_PAUSE_S = 0.25
"""Pause before a read's next try on another replica (times the try's number): the router drops a dead
replica as soon as a call to it fails, the controller replaces it within seconds."""


class Failed(Exception):
    """A forwarded call that ended with ``status`` (already made safe to show a client)."""

    def __init__(self, status: Status) -> None:
        super().__init__(status.details)
        self.status = status


class Raw:
    """An already serialized message: Serve's replica calls SerializeToString on what a method yields."""

    __slots__ = ("data",)

    def __init__(self, data: bytes) -> None:
        self.data = data

    def SerializeToString(self) -> bytes:
        return self.data


class _Held:
    """A scene (or shard) a replica holds for Ray's multiplexer; eviction unloads it from the replica."""

    def __init__(self, core: HostCore, scene: str) -> None:
        self.core, self.scene = core, scene

    def __del__(self) -> None:
        self.core.unload(self.scene)


def build_app(cfg: ServerConfig, cc: ClusterConfig, encoder_factory=None):
    """The bound Serve application (``serve.run(build_app(...))``); ``encoder_factory`` replaces the
    text encoder loader (tests), and must be picklable."""
    cfg.validate()
    cc.validate()
    autoscaling = {
        "min_replicas": cc.min_replicas,
        "max_replicas": cc.max_replicas,
        "target_ongoing_requests": cc.target_ongoing_requests,
    }

    @serve.deployment(
        name="SceneHost",
        autoscaling_config=autoscaling,
        max_ongoing_requests=cc.max_ongoing_requests,
        max_queued_requests=cc.max_queued_requests,
        ray_actor_options={"num_cpus": cc.replica_cpus, "num_gpus": cc.replica_gpus},
    )
    class SceneHost:
        def __init__(self) -> None:
            self.core = HostCore(cfg, encoder_factory)
            if cfg.preload:  # Serve routes nothing here until the constructor returns
                self.core.warm_up()
            self.replica = serve.get_replica_context().replica_id.unique_id
            """Sent back as trailing metadata (REPLICA_KEY): which replica answered."""

        @serve.multiplexed(max_num_models_per_replica=cc.scenes_per_replica)
        async def held(self, scene: str) -> _Held:
            return _Held(self.core, scene)

        async def _hold(self) -> None:
            scene = serve.get_multiplexed_model_id()
            if scene:
                await self.held(scene)

        async def _run(self, fn, *args):
            """fn(*args) in a worker thread once this replica holds the request's scene."""
            await self._hold()
            return await asyncio.to_thread(fn, *args)

        async def ping(self) -> str:
            """Health: this replica answers (its id)."""
            return self.replica

        async def unary(self, method: str, request: bytes):
            return self.replica, await self._run(self.core.unary, method, request)

        async def stream(self, method: str, request: bytes):
            await self._hold()
            yield self.replica
            for item in await asyncio.to_thread(self.core.stream, method, request):
                yield item

        async def plan_text(self, scene: str, request: bytes):
            return await self._run(self.core.plan_sharded_text, scene, request)

        async def shard_text(self, scene: str, folder: str, query):
            return await self._run(self.core.shard_text, scene, folder, query)

        async def finish_text(self, plan, parts):
            return await self._run(self.core.finish_sharded_text, plan, parts)

        async def plan_render(self, scene: str, request: bytes):
            return await self._run(self.core.plan_sharded_render, scene, request)

        async def shard_layer(self, scene: str, folder: str, plan):
            return await self._run(self.core.shard_layer, scene, folder, plan)

        async def finish_render(self, plan, layers):
            return await self._run(self.core.finish_sharded_render, plan, layers)

    @serve.deployment(
        name="FmgsIngress",
        num_replicas=cc.ingress_replicas,
        max_ongoing_requests=max(64, cfg.max_concurrent_rpcs),
        ray_actor_options={"num_cpus": 0},
    )
    class FmgsIngress:
        def __init__(self, host) -> None:
            self.host = host
            read, admin = read_tokens(cfg.token_file), read_tokens(cfg.admin_token_file)
            # Serve's gRPC proxy listens on every interface: admin calls are open only when told.
            self.auth = TokenAuth(read, admin, cfg.health_open, cfg.scene_health_open, cfg.admin_open)

        # -------------------------------------------------------------- plumbing

        def _refused(self, method: str, request, grpc_context) -> bool:
            """Set the call's code and return True when the token or the request size refuses it."""
            token = bearer_token(grpc_context.invocation_metadata())
            refused = self.auth.refusal(f"/{SERVICE}/{method}", token)
            if refused is None and request is not None and request.ByteSize() > cfg.max_receive_bytes:
                refused = (
                    grpc.StatusCode.RESOURCE_EXHAUSTED,
                    f"request of {request.ByteSize()} bytes is over max_receive_bytes "
                    f"({cfg.max_receive_bytes})",
                )
            if refused is None:
                return False
            grpc_context.set_code(refused[0])
            grpc_context.set_details(refused[1])
            return True

        @staticmethod
        def _fail(status: Status, grpc_context) -> None:
            grpc_context.set_code(getattr(grpc.StatusCode, status.code))
            grpc_context.set_details(status.details)

        async def _forward(self, method: str, call):
            """``await call()`` (a call to the scene replicas), tried again on another replica while a
            read's replica is lost (ClusterConfig.read_attempts); Failed with a status of ours else."""
            for attempt in range(1, cc.read_attempts + 1):
                try:
                    return await call()
                except asyncio.CancelledError:
                    raise
                except Exception as e:  # every failure becomes a status of ours
                    status = _logged(method, attempt, e)
                    if attempt == cc.read_attempts or not retryable(method, status):
                        raise Failed(status) from None
                    _retrying(method, attempt, status)
                await asyncio.sleep(RETRY_PAUSE_S * attempt)

        async def _unary(self, method: str, request, grpc_context, scene: str = ""):
            empty = getattr(pb, RESPONSE_TYPES[method])()
            if self._refused(method, request, grpc_context):
                return empty
            h = self.host.options(multiplexed_model_id=scene) if scene else self.host
            data = request.SerializeToString()
            try:
                replica, out = await self._forward(method, lambda: h.unary.remote(method, data))
            except Failed as f:
                self._fail(f.status, grpc_context)
                return empty
            grpc_context.set_trailing_metadata([(REPLICA_KEY, replica)])
            if isinstance(out, Status):
                self._fail(out, grpc_context)
                return empty
            return Raw(out)

        def _open(self, method: str, request):
            """The forwarded call's items (a Ray stream, or a list for sharded scenes)."""
            scene = request.scene
            # The repository path is readable on every node: no round trip to a replica to ask.
            sharded = method in ("TextQuery", "Render") and sharded_scene(cfg.models, scene)
            if sharded and method == "TextQuery":
                return self._sharded_text(scene, request)
            if sharded:
                return self._sharded_render(scene, request)
            h = self.host.options(multiplexed_model_id=scene, stream=True)
            return h.stream.remote(method, request.SerializeToString())

        async def _stream(self, method: str, request, grpc_context):
            if self._refused(method, request, grpc_context):
                raise CallFailed(grpc_context.details())
            # A read is tried again on another replica if its replica is lost before the first message
            # reached the client (after that the client holds part of an answer: it gets UNAVAILABLE).
            for attempt in range(1, cc.read_attempts + 1):
                sent = False
                try:
                    items = self._open(method, request)
                    if asyncio.iscoroutine(items):
                        items = await items
                    async for item in _aiter(items):
                        if isinstance(item, str):
                            grpc_context.set_trailing_metadata([(REPLICA_KEY, item)])
                            continue
                        if isinstance(item, Status):
                            self._fail(item, grpc_context)
                            raise CallFailed(item.details)
                        sent = True
                        yield Raw(item)
                    return
                except (CallFailed, asyncio.CancelledError):
                    raise
                except Exception as e:  # every failure becomes a status of ours
                    status = _logged(method, attempt, e)
                    if sent or attempt == cc.read_attempts or not retryable(method, status):
                        self._fail(status, grpc_context)
                        raise CallFailed(status.details) from None
                    _retrying(method, attempt, status)
                await asyncio.sleep(RETRY_PAUSE_S * attempt)

        async def _sharded_text(self, scene: str, request) -> list:
            at = self.host.options(multiplexed_model_id=scene)
            plan = await at.plan_text.remote(scene, request.SerializeToString())
            if isinstance(plan, Status):
                return [plan]
            calls = [
                self.host.options(multiplexed_model_id=f"{scene}/{f}").shard_text.remote(scene, f, plan.query)
                for f in plan.shards
            ]
            parts = await asyncio.gather(*calls)
            return await at.finish_text.remote(plan, parts)

        async def _sharded_render(self, scene: str, request) -> list:
            at = self.host.options(multiplexed_model_id=scene)
            plan = await at.plan_render.remote(scene, request.SerializeToString())
            if isinstance(plan, Status):
                return [plan]
            calls = [
                self.host.options(multiplexed_model_id=f"{scene}/{f}").shard_layer.remote(scene, f, plan)
                for f in plan.shards
            ]
            layers = await asyncio.gather(*calls)
            return await at.finish_render.remote(plan, layers)

        # -------------------------------------------------------------- fmgs.v1.Fmgs

        async def ListScenes(self, request, grpc_context):
            return await self._unary("ListScenes", request, grpc_context)

        async def GetScene(self, request, grpc_context):
            return await self._unary("GetScene", request, grpc_context, request.scene)

        async def LoadScene(self, request, grpc_context):
            return await self._unary("LoadScene", request, grpc_context, request.scene)

        async def UnloadScene(self, request, grpc_context):
            return await self._unary("UnloadScene", request, grpc_context, request.scene)

        async def ReloadScene(self, request, grpc_context):
            return await self._unary("ReloadScene", request, grpc_context, request.scene)

        async def PointQuery(self, request, grpc_context):
            return await self._unary("PointQuery", request, grpc_context, request.scene)

        async def TextQuery(self, request, grpc_context):
            async for m in self._stream("TextQuery", request, grpc_context):
                yield m

        async def Render(self, request, grpc_context):
            async for m in self._stream("Render", request, grpc_context):
                yield m

        async def Segment(self, request, grpc_context):
            async for m in self._stream("Segment", request, grpc_context):
                yield m

        async def Geometry(self, request, grpc_context):
            async for m in self._stream("Geometry", request, grpc_context):
                yield m

        async def StreamRender(self, request_stream, grpc_context):
            """Render the latest pose received whenever the previous frame is done (poses that arrive
            meanwhile are skipped, as in ``fmgs serve``)."""
            if self._refused("StreamRender", None, grpc_context):
                raise CallFailed(grpc_context.details())
            latest: list = []
            ready = asyncio.Event()
            ended = False

            async def drain() -> None:
                nonlocal ended
                try:
                    async for req in request_stream:
                        latest[:] = [req]
                        ready.set()
                finally:
                    ended = True
                    ready.set()

            task = asyncio.create_task(drain())
            try:
                while True:
                    if not latest:
                        if ended:
                            return
                        await ready.wait()
                        ready.clear()
                        continue
                    req = latest.pop()
                    async for m in self._stream("Render", req, grpc_context):
                        yield m
            finally:
                task.cancel()

        # -------------------------------------------------------------- grpc.health.v1

        async def _health(self, request, grpc_context) -> int | None:
            token = bearer_token(grpc_context.invocation_metadata())
            refused = self.auth.health_refusal(request.service, token)
            if refused is not None:
                grpc_context.set_code(refused[0])
                grpc_context.set_details(refused[1])
                return None
            service = request.service
            if service in ("", SERVICE):
                # SERVING only while a scene replica answers (the ingress alone answers nothing).
                try:
                    await asyncio.wait_for(
                        self._forward("Check", lambda: self.host.ping.remote()), cc.health_timeout_s
                    )
                except (TimeoutError, Failed):
                    return health_pb2.HealthCheckResponse.NOT_SERVING
                return health_pb2.HealthCheckResponse.SERVING
            if not service.startswith(SERVICE + "/"):
                grpc_context.set_code(grpc.StatusCode.NOT_FOUND)
                grpc_context.set_details(f"unknown service {service[:80]!r}")
                return None
            scene = service[len(SERVICE) + 1 :]
            h = self.host.options(multiplexed_model_id=scene)
            data = pb.SceneRequest(scene=scene).SerializeToString()
            try:
                _, out = await self._forward("Check", lambda: h.unary.remote("GetScene", data))
            except Failed:
                return health_pb2.HealthCheckResponse.NOT_SERVING
            if isinstance(out, Status):
                if out.code == "NOT_FOUND":
                    self._fail(missing(scene), grpc_context)
                    return None
                return health_pb2.HealthCheckResponse.NOT_SERVING
            info = pb.SceneInfo.FromString(out)
            failed = info.state == pb.SCENE_STATE_FAILED
            return (
                health_pb2.HealthCheckResponse.NOT_SERVING
                if failed
                else health_pb2.HealthCheckResponse.SERVING
            )

        async def Check(self, request, grpc_context):
            status = await self._health(request, grpc_context)
            return health_pb2.HealthCheckResponse(status=status or 0)

        async def Watch(self, request, grpc_context):
            """The current status once (Serve's proxy cannot hold a watch open across replicas)."""
            status = await self._health(request, grpc_context)
            if status is None:
                raise CallFailed(grpc_context.details())
            yield health_pb2.HealthCheckResponse(status=status)

    return FmgsIngress.bind(SceneHost.bind())


def _logged(method: str, attempt: int, exc: Exception) -> Status:
    """The client's status for a failed forwarded call; Ray's own text goes to the server log only."""
    status = failure_status(exc)
    log.warning("%s try %d: %s (%s: %s)", method, attempt, status.code, type(exc).__name__, exc)
    return status


def _retrying(method: str, attempt: int, status: Status) -> None:
    log.warning(
        "%s: replica lost (%s), trying again on another replica (try %d)", method, status.code, attempt + 1
    )


async def _aiter(items):
    """Iterate a Ray streaming response or a plain list alike."""
    if isinstance(items, list):
        for x in items:
            yield x
        return
    async for x in items:
        yield x


def app_builder(args: dict):
    """Entry point for ``serve run``/KubeRay: ``import_path: fmgs_server.cluster.app:app_builder`` with
    ``args`` {"config": TOML path of the ServerConfig settings (optional), any ``ray_*`` ClusterConfig
    field without the prefix}."""
    import tomllib
    from pathlib import Path

    from fmgs.flags import build

    path = args.get("config")
    cfg = build(ServerConfig, tomllib.loads(Path(path).read_text()) if path else {}, str(path or "defaults"))
    fields = {k: v for k, v in args.items() if k != "config"}
    for key, where in (("app_name", "the application's name"), ("request_timeout_s", "grpc_options")):
        if key in fields:  # Serve's config decides these, not the application
            raise ValueError(f"serve config args: set {key!r} as {where} of the Serve config, not in args")
    cc = build(ClusterConfig, fields, "serve config args") if fields else ClusterConfig()
    return build_app(cfg, cc)
