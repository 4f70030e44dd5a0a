"""``fmgs-server --ray [ADDRESS]``: deploy the service on a Ray cluster and wait for SIGTERM/SIGINT."""

from __future__ import annotations

import logging
import os
import signal
import socket
import threading

from fmgs_server.cluster.config import ClusterConfig
from fmgs_server.config import ServerConfig

log = logging.getLogger("fmgs_server")

PROXY_HEALTH_ENV = {
    "RAY_SERVE_PROXY_HEALTH_CHECK_PERIOD_S": "1",
    "RAY_SERVE_PROXY_HEALTH_CHECK_TIMEOUT_S": "2",
}
"""Serve's controller checks each proxy every PERIOD s and replaces it after 3 failed checks in a row
(fixed in Ray 2.60): 10 s by default, so a lost proxy cost about 30 s; 1 s makes it about 3-5 s. Read by
the controller when it starts: set for a cluster that --ray starts, and in the environment of `ray start`
for one started separately (deploy/kuberay/rayservice.yaml does)."""


def set_proxy_health_env() -> None:
    """PROXY_HEALTH_ENV into this process's environment (values already set win): call it before the Ray
    cluster starts, so that Serve's controller inherits them."""
    for key, value in PROXY_HEALTH_ENV.items():
        os.environ.setdefault(key, value)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def check_supported(cfg: ServerConfig) -> None:
    """Settings that Serve's gRPC proxy cannot honour: a clear error instead of a silent difference."""
    if cfg.tls_cert is not None:
        raise ValueError(
            "--ray: Ray Serve's gRPC proxy has no TLS; terminate TLS in front of it (a Kubernetes "
            "Ingress or Gateway, or an envoy/nginx sidecar) and run the cluster without --tls-cert"
        )


def start_ray_serve(cfg: ServerConfig, cc: ClusterConfig, address: str | None, encoder_factory=None,
                    runtime_env: dict | None = None) -> int:  # fmt: skip
    """Connect to (or start) a Ray cluster, start Serve's gRPC proxy on cfg.port (a free one for 0) and
    deploy the application; returns the gRPC port. ``address``: None starts a local cluster."""
    check_supported(cfg)
    cfg.validate()
    cc.validate()
    # The proxy's message limit is process-wide (both directions); requests are checked against
    # max_receive_bytes in the ingress.
    os.environ.setdefault(
        "RAY_SERVE_GRPC_MAX_MESSAGE_SIZE", str(max(cfg.max_send_bytes, cfg.max_receive_bytes))
    )
    set_proxy_health_env()
    import ray
    from ray import serve
    from ray.serve.config import HTTPOptions, gRPCOptions

    from fmgs_server.cluster.app import SERVICER_FUNCTIONS, build_app

    port = cfg.port or free_port()  # Serve reads port 0 as "no gRPC"
    if not ray.is_initialized():
        ray.init(address=address, include_dashboard=False, runtime_env=runtime_env, log_to_driver=False)
    serve.start(
        http_options=HTTPOptions(host="127.0.0.1", port=0),
        grpc_options=gRPCOptions(
            port=port,
            grpc_servicer_functions=SERVICER_FUNCTIONS,
            request_timeout_s=cc.request_timeout_s or None,
        ),
    )
    serve.run(build_app(cfg, cc, encoder_factory), name=cc.app_name, route_prefix="/" + cc.app_name)
    return port


def serve_ray(cfg: ServerConfig, cc: ClusterConfig, address: str | None) -> bool:
    """Run until SIGTERM or SIGINT, then delete the application (and stop the cluster if it was local)."""
    import ray
    from ray import serve

    port = start_ray_serve(cfg, cc, address)
    print(f"fmgs serving {cfg.models} on Ray ({address or 'local cluster'}), gRPC port {port}", flush=True)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda s, f: stop.set())
    while not stop.wait(0.5):
        pass
    log.info("deleting application %s", cc.app_name)
    serve.delete(cc.app_name)
    if address is None:
        serve.shutdown()
    ray.shutdown()
    return True
