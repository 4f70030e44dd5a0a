"""Generate the Python gRPC modules from proto/ into fmgs_wire/proto (or check they are current).

The include path is mapped (``-Ifmgs_wire/proto=proto``) so the import lines protoc emits name the
package the modules live in (``fmgs_wire.proto.fmgs.v1``) and never the core ``fmgs`` package.

    python scripts/gen_proto.py           # regenerate
    python scripts/gen_proto.py --check   # exit 1 if the checked-in modules are stale
"""

from __future__ import annotations

import argparse
import filecmp
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROTO = ROOT / "proto"
PREFIX = "fmgs_wire/proto"


def generate(out: Path) -> list[Path]:
    """Write the generated modules (and package __init__ files) under ``out``; return their paths."""
    from grpc_tools import protoc

    files = sorted(p.relative_to(PROTO).as_posix() for p in PROTO.rglob("*.proto"))
    args = [
        "protoc",
        f"-I{PREFIX}={PROTO}",
        f"--python_out={out}",
        f"--pyi_out={out}",
        f"--grpc_python_out={out}",
    ]
    for f in files:
        args.append(f"{PREFIX}/{f}")
    if protoc.main(args) != 0:
        raise SystemExit("protoc failed")
    made = []
    for d in [out / PREFIX, *[p for p in (out / PREFIX).rglob("*") if p.is_dir()]]:
        init = d / "__init__.py"
        if not init.exists():
            init.write_text("")
    for p in sorted((out / PREFIX).rglob("*")):
        if p.is_file():
            made.append(p.relative_to(out))
    return made


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="compare instead of writing")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        made = generate(tmp)
        if a.check:
            stale = [
                str(r) for r in made if not (ROOT / r).is_file() or not filecmp.cmp(tmp / r, ROOT / r, False)
            ]
            have = {
                p.relative_to(ROOT)
                for p in (ROOT / PREFIX).rglob("*")
                if p.is_file() and "__pycache__" not in p.parts
            }
            stale += [str(p) for p in sorted(have - set(made))]
            if stale:
                print(
                    "generated protobuf modules are stale; run python scripts/gen_proto.py:",
                    *stale,
                    sep="\n  ",
                )
                return 1
            print(f"protobuf modules current ({len(made)} files)")
            return 0
        for r in made:
            (ROOT / r).parent.mkdir(parents=True, exist_ok=True)
            (ROOT / r).write_bytes((tmp / r).read_bytes())
        print(f"wrote {len(made)} files under {PREFIX}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
