"""Start, run and stop the gRPC server: service, health (per scene too), reflection, TLS, tokens."""

from __future__ import annotations

import logging
import signal
import threading
from concurrent import futures
from dataclasses import dataclass
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

    @property
    def address(self) -> str:
        host = self.config.host if self.config.host not in ("0.0.0.0", "::", "[::]") else "127.0.0.1"
        return f"{host}:{self.port}"

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


def _text_encoder(device: str, downloads: bool = True):
    """Loads a scene's text encoder: a local folder, the hub cache, else a download unless ``downloads``
    is off (ServerConfig.model_downloads; HF_HUB_OFFLINE/FMGS_OFFLINE also forbid it)."""

    def load(encoder_id: str):
        from fmgs.features.text import load_text_encoder

        return load_text_encoder(encoder_id, device=device, offline=None if downloads else True)

    return load


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


def start_server(cfg: ServerConfig, encoder_factory=None) -> RunningServer:
    """Build and start a server for ``cfg`` (port 0 picks a free port; see ``RunningServer.port``)."""
    cfg.validate()
    read, admin = read_tokens(cfg.token_file), read_tokens(cfg.admin_token_file)
    health_servicer = health.HealthServicer(experimental_non_blocking=True)

    def on_change(name: str, state: str) -> None:
        status = (
            health_pb2.HealthCheckResponse.NOT_SERVING
            if state in (FAILED, "removed")
            else health_pb2.HealthCheckResponse.SERVING
        )
        health_servicer.set(scene_health_name(name), status)

    service = make_service(cfg, encoder_factory, on_change)
    repo, encoders = service.repo, service.encoders

    auth = TokenAuth(read, admin, cfg.health_open, cfg.scene_health_open)
    interceptors = [auth] if (read or admin) else []
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
    address = f"{cfg.host}:{cfg.port}" if ":" not in cfg.host else f"[{cfg.host}]:{cfg.port}"
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
    for slot in repo.scan():
        on_change(slot.name, slot.state)
    health_servicer.set("", health_pb2.HealthCheckResponse.SERVING)
    health_servicer.set(SERVICE, health_pb2.HealthCheckResponse.SERVING)
    server.start()
    running = RunningServer(server, port, cfg, service, health_servicer)
    if cfg.preload:
        for slot in repo.scan():
            try:
                engine = repo.get(slot.name)
                encoders.encoder(engine.encoder_id)
                encoders.negatives(engine.encoder_id, tuple(negative_names(engine.manifest.label_names)))
                log.info("scene %s: kernels warmed up in %.1f s", slot.name, engine.warm_up())
            except Exception as e:  # reported per scene in the listing and health
                log.warning("preload of %s failed: %s", slot.name, e)
    log.info("serving %s on %s (%d scenes)", cfg.models, running.address, len(repo.scan()))
    return running


def serve(cfg: ServerConfig) -> bool:
    """Run until SIGTERM or SIGINT, then drain in-flight requests for ``grace_s`` seconds; False when the
    transport had to be abandoned (the caller must then end the process: its threads may never return)."""
    running = start_server(cfg)
    print(f"fmgs serving {cfg.models} on {running.address}", flush=True)
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
