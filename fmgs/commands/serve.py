"""``fmgs serve``: the ``fmgs-server`` command in this process's place (the core never imports the server).

Its arguments are not parsed here: ``fmgs.cli.main`` hands everything after ``serve`` to ``run``, which
execs ``python -m fmgs_server.cli``; the subparser only lists the command in ``fmgs --help``."""

from __future__ import annotations

import sys


def add_parser(sub) -> None:
    sub.add_parser(
        "serve",
        help="serve scene packages over gRPC: the fmgs-server command (needs fmgs[server]); "
        "`fmgs serve --help` lists its flags",
        add_help=False,
    )


def run(argv: list[str]) -> int:
    """``fmgs serve ARGS`` execs ``fmgs-server ARGS`` (same process id): the core never imports the server."""
    import importlib.util
    import os

    if importlib.util.find_spec("fmgs_server") is None or importlib.util.find_spec("grpc") is None:
        print(
            "fmgs serve: the server is not installed: pip install 'fmgs[server]' (then run fmgs-server)",
            file=sys.stderr,
        )
        return 2
    sys.stdout.flush()
    os.execv(sys.executable, [sys.executable, "-m", "fmgs_server.cli", *argv])
    return 0  # pragma: no cover - exec does not return
