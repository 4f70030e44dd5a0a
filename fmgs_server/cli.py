"""The ``fmgs-server`` command (also ``fmgs serve``): every ServerConfig field is a flag and a TOML key.

fmgs-server --models models --port 50051 --index-rank 64 --index-rerank 4
fmgs-server --config server.toml --port 0      # flags override the file, the file the defaults
"""

from __future__ import annotations

import argparse
import sys

from fmgs.flags import UNSET, add_flags, build, config_from
from fmgs_server.cluster.config import ClusterConfig
from fmgs_server.config import MiB, ServerConfig


def build_parser(prog: str = "fmgs-server") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog,
        description="Serve the scene packages of a model repository over gRPC until SIGTERM/SIGINT.",
    )
    p.add_argument("--config", help="TOML file of settings (keys are the flag names with _; [index] table)")
    p.add_argument("--log-level", default="INFO", help="logging level (default: INFO)")
    p.add_argument(
        "--memory-budget-mb",
        type=float,
        help="the same as --memory-budget-bytes, in MiB",
    )
    add_flags(p, ServerConfig)
    p.add_argument(
        "--precompile",
        action="store_true",
        help="compile the kernels on every scene into numba's cache (NUMBA_CACHE_DIR) and exit, serving "
        "nothing and loading no text encoder (image builds fill their cache with it)",
    )
    p.add_argument(
        "--ray",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="serve on a Ray cluster through Ray Serve's gRPC proxy (needs fmgs[ray]): ADDRESS of a "
        "running cluster ('auto' finds the local node's), or none to start a local one",
    )
    add_flags(p.add_argument_group("Ray cluster (with --ray; flags only)"), ClusterConfig, prefix="ray.")
    return p


def cluster_config_from_args(a: argparse.Namespace) -> ClusterConfig:
    """The ClusterConfig of the --ray-* flags; ValueError names a bad setting."""
    given = {k.split(".", 1)[1]: v for k, v in vars(a).items() if k.startswith("ray.") and v is not UNSET}
    cc = build(ClusterConfig, given, "flags")
    cc.validate()
    return cc


def config_from_args(a: argparse.Namespace) -> ServerConfig:
    """The ServerConfig the parsed flags (and --config file) describe; ValueError names a bad setting."""
    if a.memory_budget_mb is not None:
        a.memory_budget_bytes = int(a.memory_budget_mb * MiB)
    cfg = config_from(ServerConfig, a, a.config)
    cfg.validate()
    return cfg


def main(argv: list[str] | None = None, prog: str = "fmgs-server") -> int:
    a = build_parser(prog).parse_args(argv)
    try:
        cfg = config_from_args(a)
        cc = cluster_config_from_args(a)
    except ValueError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return 2
    import logging

    log_format = "%(asctime)s %(levelname)s %(name)s: %(message)s"
    if a.precompile:
        logging.basicConfig(level=a.log_level.upper(), format=log_format)
        from fmgs_server.server import precompile

        return 0 if precompile(cfg) else 1
    if a.ray is not None:
        logging.basicConfig(
            level=a.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
        )
        from fmgs_server.cluster.launch import serve_ray

        try:
            serve_ray(cfg, cc, None if a.ray == "local" else a.ray)
        except ImportError as e:
            print(f"{prog}: error: --ray needs Ray Serve: pip install 'fmgs[ray]' ({e})", file=sys.stderr)
            return 2
        except ValueError as e:
            print(f"{prog}: error: {e}", file=sys.stderr)
            return 2
        return 0

    from fmgs_server.server import serve

    logging.basicConfig(level=a.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    serve(cfg)
    # Exit now: a handler thread left stuck in the transport (after garbage on a bidirectional stream,
    # seen with grpcio 1.85.1) would block the interpreter's exit, which joins the pool's threads. The
    # server writes no files, so nothing is lost; the drain has already happened (or timed out).
    import os

    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
