"""The ``fmgs`` command line: thin wrappers over the library, one module per command in fmgs.commands
(``add_parser`` registers a command's flags, ``run`` runs it)."""

from __future__ import annotations

import argparse
import importlib
import sys

from fmgs.commands import COMMANDS
from fmgs.commands.common import auto_device
from fmgs.commands.serve import run as serve

_CORE_MODULES = ("torch", "numba", "safetensors", "plyfile", "scipy", "PIL", "tqdm")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="fmgs", description="FMGS: foundation-model embedded 3D Gaussian Splatting"
    )
    sub = p.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        importlib.import_module(f"fmgs.commands.{name}").add_parser(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["serve"]:
        return serve(argv[1:])
    args = build_parser().parse_args(argv)
    try:
        from fmgs.errors import FmgsError

        if getattr(args, "device", None) == "auto":
            args.device = auto_device()
        try:
            return args.func(args)
        except FmgsError as e:
            print(f"fmgs: error: {e}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:  # outputs are written atomically: nothing half-written is left
            print(f"fmgs: {args.command}: interrupted", file=sys.stderr)
            return 130
        except BrokenPipeError:  # the reader went away (`fmgs info ... | head`): not an error of ours
            import os

            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return 141
    except ModuleNotFoundError as e:
        if e.name not in _CORE_MODULES:
            raise
        print(
            f"fmgs: `fmgs {args.command}` needs the core library ({e.name} is missing): "
            "pip install 'fmgs[core]' (the client-only install has fmgs-client)",
            file=sys.stderr,
        )
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
