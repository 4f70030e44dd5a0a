"""Start, run and stop the gRPC server: service, health (per scene too), reflection, TLS, tokens."""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections.abc import Callable
from concurrent import futures
from dataclasses import dataclass, field
from pathlib import Path

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from fmgs.query.engine import EngineConfig, SceneEngine
from fmgs.query.presence import negative_names
from fmgs_server.auth import TokenAuth, read_tokens
from fmgs_server.config import ServerConfig
from fmgs_server.encoders import EncoderCache
from fmgs_server.repository import FAILED, SceneRepository
from fmgs_server.service import FmgsService
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb

log = logging.getLogger("fmgs_server")
SERVICE = pb.DESCRIPTOR.services_by_name["Fmgs"].full_name  # "fmgs.v1.Fmgs"
STOP_MARGIN_S = 2.0
"""How long past the grace period a stop may take before the server gives up on the transport."""
WILDCARDS = ("0.0.0.0", "::", "[::]")
"""Hosts that bind every interface."""
SERVING = health_pb2.HealthCheckResponse.SERVING
NOT_SERVING = health_pb2.HealthCheckResponse.NOT_SERVING


def scene_health_name(scene: str) -> str:
    """The health-service name of one scene."""
    return f"{SERVICE}/{scene}"


@dataclass
class RunningServer:
    """A started server."""

    server: grpc.Server
    port: int
    config: ServerConfig
    service: FmgsService
    health: health.HealthServicer
    ready: threading.Event = field(default_factory=threading.Event)
    """Set once the preload's warm-up has ended (at once without preload): health then says SERVING."""

    @property
    def address(self) -> str:
        """Where a client on this machine connects (loopback when the server binds every interface)."""
        host = self.config.host if self.config.host not in WILDCARDS else "127.0.0.1"
        return f"{host}:{self.port}"

    @property
    def bound(self) -> str:
        """Where the server listens, as bound (0.0.0.0:PORT when it binds every interface)."""
        return _join(self.config.host, self.port)

    def describe(self) -> str:
        """``MODELS on BOUND``, with the address to connect to from this machine when they differ; the
        last word is always that address (fmgs_server.launch reads it)."""
        where = self.bound
        if self.config.host in WILDCARDS:
            where += f" (every interface; from this machine: {self.address})"
        return f"{self.config.models} on {where}"

    def stop(self, grace: float | None = None) -> bool:
        """Refuse new calls, let in-flight ones finish within ``grace`` seconds, then stop.

        Bounded whatever the transport does: grpcio's stop can wait forever after malformed messages on
        a bidirectional stream, so this waits ``grace + STOP_MARGIN_S`` at most. True when the server
        stopped within that; False when it gave up (``serve`` then exits the process anyway).
        """
        grace = self.config.grace_s if grace is None else grace
        self.health.enter_graceful_shutdown()
        done = self.server.stop(grace).wait(grace + STOP_MARGIN_S)
        if not done:
            log.warning(
                "the transport did not stop within %.1f s of the grace period; giving up", STOP_MARGIN_S
            )
        return done

    def wait(self) -> None:
        self.server.wait_for_termination()


RAW_REQUESTS = ("StreamRender",)
"""Methods whose request messages reach the service as bytes and are decoded there, so a malformed
message on an open stream gets INVALID_ARGUMENT (and an honest log line) instead of grpc's INTERNAL abort."""

_HANDLERS = {
    (False, False): grpc.unary_unary_rpc_method_handler,
    (False, True): grpc.unary_stream_rpc_method_handler,
    (True, False): grpc.stream_unary_rpc_method_handler,
    (True, True): grpc.stream_stream_rpc_method_handler,
}


def add_service(service: FmgsService, server: grpc.Server) -> None:
    """Register ``fmgs.v1.Fmgs`` from its descriptor (as the generated add_FmgsServicer_to_server does,
    except for RAW_REQUESTS)."""
    handlers = {}
    for m in pb.DESCRIPTOR.services_by_name["Fmgs"].methods:
        request, response = getattr(pb, m.input_type.name), getattr(pb, m.output_type.name)
        handlers[m.name] = _HANDLERS[(m.client_streaming, m.server_streaming)](
            getattr(service, m.name),
            request_deserializer=None if m.name in RAW_REQUESTS else request.FromString,
            response_serializer=response.SerializeToString,
        )
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(SERVICE, handlers),))
    server.add_registered_method_handlers(SERVICE, handlers)


NO_DOWNLOADS = (
    "this server's --no-model-downloads, or model_downloads = false in its --config file; restart it with "
    "--model-downloads to let it fetch models, or pre-fetch this one into its hub cache"
)
"""Why a server does not download a model, and what to change (in the error a scene's load gives)."""


def _text_encoder(device: str, downloads: bool = True):
    """Loads a scene's text encoder: a local folder, the hub cache, else a download unless ``downloads``
    is off (ServerConfig.model_downloads; HF_HUB_OFFLINE/FMGS_OFFLINE also forbid it). Given a ModelPin
    (the revision and files a scene recorded), it loads that revision and refuses other bytes."""

    def load(encoder_id: str, pin=None):
        from fmgs.features.text import load_text_encoder

        offline = None if downloads else NO_DOWNLOADS
        if pin is None:
            return load_text_encoder(encoder_id, device=device, offline=offline)
        return load_text_encoder(
            encoder_id, device=device, offline=offline, revision=pin.revision, expect=pin.expect
        )

    return load


def _join(host: str, port: int) -> str:
    host = host.strip("[]")
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def warm_scene(service: FmgsService, name: str) -> float:
    """Make scene ``name`` ready for its first calls: load it, its text encoder and its presence
    negatives, and run its kernels once (numba compiles them, or reads them from its cache); returns the
    seconds taken. Raises what a load raises."""
    t0 = time.perf_counter()
    engine = service.repo.get(name)
    model = service.text_model(engine)  # at the revision the scene was built with
    service.encoders.encoder(model)
    service.encoders.negatives(model, tuple(negative_names(engine.manifest.label_names)))
    engine.warm_up()
    return time.perf_counter() - t0


def precompile(cfg: ServerConfig) -> bool:
    """Run every scene's kernels once, so that numba compiles them into its on-disk cache (NUMBA_CACHE_DIR,
    else beside the code or in the user's cache folder) for later starts; no text encoder is loaded.
    False when a scene failed to load or to run."""
    service = make_service(cfg, lambda encoder_id: None)
    ok = True
    for slot in service.repo.scan():
        try:
            log.info("scene %s: kernels compiled in %.1f s", slot.name, service.repo.get(slot.name).warm_up())
        except Exception as e:  # every scene is tried; the exit status says one failed
            log.error("scene %s: %s", slot.name, e)
            ok = False
    return ok


class Readiness:
    """The health statuses: the server's ("" and fmgs.v1.Fmgs) and each scene's (fmgs.v1.Fmgs/<scene>).

    A scene is NOT_SERVING while it is waiting for or in its warm-up (preload), when it failed to load or
    to warm up, and once removed; SERVING otherwise (a scene not loaded yet loads on its first call). The
    server is NOT_SERVING until every scene's warm-up has ended, failed or not.
    """

    def __init__(self, servicer: health.HealthServicer) -> None:
        self.servicer = servicer
        self.warming: set[str] = set()
        self._lock = threading.Lock()

    def server(self, status) -> None:
        self.servicer.set("", status)
        self.servicer.set(SERVICE, status)

    def scene(self, name: str, state: str) -> None:
        """The repository's on_change: scene ``name`` is now ``state``."""
        with self._lock:
            if state == "removed":
                self.warming.discard(name)
            ok = state not in (FAILED, "removed") and name not in self.warming
            self.servicer.set(scene_health_name(name), SERVING if ok else NOT_SERVING)

    def warming_up(self, names: list[str]) -> None:
        with self._lock:
            self.warming |= set(names)
            for name in names:
                self.servicer.set(scene_health_name(name), NOT_SERVING)

    def warmed(self, name: str, ok: bool) -> None:
        with self._lock:
            self.warming.discard(name)
            self.servicer.set(scene_health_name(name), SERVING if ok else NOT_SERVING)


def _preload(
    service: FmgsService, readiness: Readiness, names: list[str], warm, ready: threading.Event
) -> None:
    """Warm up every scene of ``names`` in turn, then say SERVING for the server and set ``ready``."""
    t0 = time.perf_counter()
    try:
        for name in names:
            try:
                log.info("scene %s: warmed up in %.1f s", name, warm(service, name))
                readiness.warmed(name, True)
            except Exception as e:  # reported per scene: the listing and its health say it failed
                log.warning("scene %s: preload failed, its health stays NOT_SERVING: %s", name, e)
                readiness.warmed(name, False)
    finally:
        readiness.server(SERVING)
        ready.set()
    log.info("preload done in %.1f s: health SERVING", time.perf_counter() - t0)


def make_service(cfg: ServerConfig, encoder_factory=None, on_change=None) -> FmgsService:
    """The service over ``cfg.models`` with its repository and text-encoder cache (no transport): what
    ``start_server`` serves, and what each Ray replica holds (fmgs_server.cluster)."""
    ecfg = EngineConfig(cfg.index, backend=cfg.backend, device=cfg.device)
    repo = SceneRepository(
        cfg.models,
        lambda p: SceneEngine.open(p, ecfg),
        cfg.memory_budget_bytes,
        cfg.reload_check_s,
        on_change,
    )
    encoders = EncoderCache(encoder_factory or _text_encoder(cfg.device, cfg.model_downloads), cfg.text_cache)
    return FmgsService(cfg, repo, encoders)


def start_server(
    cfg: ServerConfig,
    encoder_factory=None,
    warm: Callable[[FmgsService, str], float] = warm_scene,
    wait: bool = True,
) -> RunningServer:
    """Build and start a server for ``cfg`` (port 0 picks a free port; see ``RunningServer.port``).

    With ``cfg.preload`` the transport starts first, answering health NOT_SERVING, then ``warm(service,
    scene)`` runs on every scene; ``wait`` returns only after that, else at once (``RunningServer.ready``
    is set when it ends).
    """
    cfg.validate()
    read, admin = read_tokens(cfg.token_file), read_tokens(cfg.admin_token_file)
    health_servicer = health.HealthServicer(experimental_non_blocking=True)
    readiness = Readiness(health_servicer)
    service = make_service(cfg, encoder_factory, readiness.scene)
    repo = service.repo

    auth = TokenAuth(read, admin, cfg.health_open, cfg.scene_health_open, cfg.admin_without_token)
    interceptors = [auth]
    server = grpc.server(
        futures.ThreadPoolExecutor(max_workers=cfg.max_concurrent_rpcs + 4, thread_name_prefix="fmgs-rpc"),
        interceptors=interceptors,
        options=[
            ("grpc.max_receive_message_length", cfg.max_receive_bytes),
            ("grpc.max_send_message_length", cfg.max_send_bytes),
            ("grpc.so_reuseport", 0),
        ],
        maximum_concurrent_rpcs=cfg.max_concurrent_rpcs,
    )
    add_service(service, server)
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    reflection.enable_server_reflection(
        (SERVICE, health_pb2.DESCRIPTOR.services_by_name["Health"].full_name, reflection.SERVICE_NAME), server
    )
    address = _join(cfg.host, cfg.port)
    if cfg.tls_cert is not None:
        key, cert = Path(cfg.tls_key).read_bytes(), Path(cfg.tls_cert).read_bytes()
        ca = Path(cfg.client_ca).read_bytes() if cfg.client_ca else None
        creds = grpc.ssl_server_credentials(
            [(key, cert)], root_certificates=ca, require_client_auth=ca is not None
        )
        port = server.add_secure_port(address, creds)
    else:
        port = server.add_insecure_port(address)
    if port == 0:
        raise OSError(f"cannot bind {address}")
    names = [slot.name for slot in repo.scan()]
    if cfg.preload:
        readiness.warming_up(names)
    for slot in repo.scan():
        readiness.scene(slot.name, slot.state)
    readiness.server(NOT_SERVING if cfg.preload else SERVING)
    server.start()
    running = RunningServer(server, port, cfg, service, health_servicer)
    if not admin and cfg.admin_without_token and not cfg.admin_open:
        log.info("admin calls answered without a token: the server binds loopback only")
    elif not admin and not cfg.admin_open:
        log.info("admin calls are closed (no --admin-token-file)")
    if cfg.preload:
        log.info("warming up %d scenes; health NOT_SERVING until done", len(names))
        preload = threading.Thread(
            target=_preload, args=(service, readiness, names, warm, running.ready), name="fmgs-preload"
        )
        preload.daemon = True
        preload.start()
        if wait:
            running.ready.wait()
    else:
        running.ready.set()
    log.info("serving %s (%d scenes)", running.describe(), len(names))
    return running


def serve(cfg: ServerConfig) -> bool:
    """Run until SIGTERM or SIGINT, then drain in-flight requests for ``grace_s`` seconds; False when the
    transport had to be abandoned (the caller must then end the process: its threads may never return)."""
    running = start_server(cfg)
    print(f"fmgs serving {running.describe()}", flush=True)
    stop = threading.Event()

    def handle(signum, frame):
        log.info("signal %d: draining for up to %.1f s", signum, cfg.grace_s)
        stop.set()

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, handle)
    while not stop.wait(0.5):  # short waits keep the main thread responsive to signals
        pass
    clean = running.stop()
    log.info("stopped" if clean else "stopped (in-flight calls abandoned)")
    return clean
