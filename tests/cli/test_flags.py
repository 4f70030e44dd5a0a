"""Flags and TOML files generated from dataclass configs; the commands start without torch."""

from __future__ import annotations

import argparse
import dataclasses
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from fmgs.flags import add_flags, config_from, field_docs
from fmgs_server.cli import build_parser, config_from_args
from fmgs_server.config import MiB, ServerConfig

ROOT = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class Inner:
    rank: int = 64
    """Basis size."""
    name: str = "a"


@dataclass(frozen=True)
class Outer:
    path: Path = Path("models")
    """Where scenes live."""
    ratio: float = 0.5
    """A fraction."""
    token: Path | None = None
    """Optional file."""
    on: bool = True
    """A switch."""
    inner: Inner = field(default_factory=Inner)
    """Nested settings."""


def _parse(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_flags(p, Outer)
    return p.parse_args(argv)


def test_docs_and_defaults_come_from_the_dataclass():
    assert field_docs(Outer)["ratio"] == "A fraction."
    assert field_docs(Inner) == {"rank": "Basis size."}
    assert config_from(Outer, _parse([])) == Outer()


def test_flags_override_the_file_which_overrides_defaults(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text('ratio = 0.25\ntoken = "t.txt"\n[inner]\nrank = 8\nname = "b"\n')
    cfg = config_from(Outer, _parse(["--inner-rank", "16", "--no-on"]), f)
    assert cfg == Outer(Path("models"), 0.25, Path("t.txt"), False, Inner(16, "b"))
    assert config_from(Outer, _parse(["--token", "none"])).token is None


@pytest.mark.parametrize(
    ("text", "word"),
    [("ratio = 'x'", "ratio"), ("inner = 3", "inner"), ("nope = 1", "nope"), ("[inner]\nrank = 1.5", "rank")],
)
def test_bad_file_values_are_named(tmp_path, text, word):
    f = tmp_path / "c.toml"
    f.write_text(text)
    with pytest.raises(ValueError, match=word):
        config_from(Outer, _parse([]), f)


def test_every_server_setting_is_a_flag():
    defaults = ServerConfig()
    argv, expect = [], {}
    for f in dataclasses.fields(ServerConfig):
        v = getattr(defaults, f.name)
        if dataclasses.is_dataclass(v):
            continue
        flag = "--" + f.name.replace("_", "-")
        if f.name == "admin_open":
            continue  # contradicts admin_token_file (set below): checked on its own
        if isinstance(v, bool):
            argv.append(flag if not v else "--no-" + flag[2:])
            expect[f.name] = not v
        elif f.name in ("tls_cert", "tls_key", "client_ca", "backend", "presence_rule"):
            continue  # validated (these go together; a backend or rule name): set below
        elif isinstance(v, int | float):
            argv += [flag, str(v + 1)]
            expect[f.name] = v + 1
        else:
            argv += [flag, "x"]
            expect[f.name] = Path("x") if f.type in ("Path", "Path | None") else "x"
    argv += ["--tls-cert", "c.pem", "--tls-key", "k.pem", "--client-ca", "ca.pem", "--index-rerank", "3"]
    argv += ["--default-top-k", "5", "--backend", "triton", "--presence-rule", "each"]
    expect["default_top_k"] = 5
    expect["backend"] = "triton"
    expect["presence_rule"] = "each"  # the quorum set above needs it
    cfg = config_from_args(build_parser().parse_args(argv))
    for k, v in expect.items():
        assert getattr(cfg, k) == v, k
    assert cfg.index.rerank == 3 and cfg.tls_cert == Path("c.pem")
    assert config_from_args(build_parser().parse_args(["--admin-open"])).admin_open
    mb = config_from_args(build_parser().parse_args(["--memory-budget-mb", "2"]))
    assert mb.memory_budget_bytes == 2 * MiB


def test_server_config_file_and_validation(tmp_path):
    f = tmp_path / "server.toml"
    f.write_text('port = 0\nhost = "0.0.0.0"\n[index]\nrank = 0\n')
    cfg = config_from_args(build_parser().parse_args(["--config", str(f), "--port", "7"]))
    assert (cfg.port, cfg.host, cfg.index.rank) == (7, "0.0.0.0", 0)
    with pytest.raises(ValueError, match="port"):
        config_from_args(build_parser().parse_args(["--port", "70000"]))
    with pytest.raises(ValueError, match="backend must be one of"):
        config_from_args(build_parser().parse_args(["--backend", "gpu"]))


def test_server_backends_are_the_rasterisers():
    from fmgs.render import BACKENDS

    for name in BACKENDS:  # the server checks names without importing torch: the same list
        ServerConfig(backend=name).validate()


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60)


def test_fmgs_help_imports_no_torch():
    p = subprocess.run(
        [sys.executable, "-X", "importtime", "-c", "import fmgs.cli; fmgs.cli.build_parser().format_help()"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
    )
    assert p.returncode == 0, p.stderr
    imported = {line.split("|")[-1].strip() for line in p.stderr.splitlines() if "|" in line}
    assert not {m for m in imported if m.split(".")[0] in ("torch", "numba", "fmgs_server", "fmgs_client")}


def test_commands_without_the_core_say_what_to_install():
    p = _run(
        "import sys; sys.modules['torch'] = None; from fmgs.cli import main; sys.exit(main(['info', 'x']))"
    )
    assert p.returncode == 2 and "pip install 'fmgs[core]'" in p.stderr and "Traceback" not in p.stderr
    p = _run(
        "import sys, importlib.util as u; f = u.find_spec; u.find_spec = lambda n, *a: None if n == 'grpc' "
        "else f(n, *a); from fmgs.cli import main; sys.exit(main(['serve']))"
    )
    assert p.returncode == 2 and "pip install 'fmgs[server]'" in p.stderr


def test_core_never_imports_the_server_or_the_client():
    offenders = []
    for path in (ROOT / "fmgs").rglob("*.py"):
        for line in path.read_text().splitlines():
            s = line.strip()
            if s.startswith(("import fmgs_", "from fmgs_server", "from fmgs_client")):
                offenders.append(f"{path.relative_to(ROOT)}: {s}")
    assert offenders == []
