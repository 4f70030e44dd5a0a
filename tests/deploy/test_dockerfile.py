"""No Docker engine runs here: check that every path and command the Dockerfile names exists and parses."""

from __future__ import annotations

import fnmatch
import json
import re
import shlex
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _instructions() -> list[tuple[str, str]]:
    text = (ROOT / "Dockerfile").read_text().replace("\\\n", " ")
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            op, _, rest = line.partition(" ")
            out.append((op.upper(), rest.strip()))
    return out


def test_copied_paths_exist():
    copies = [rest for op, rest in _instructions() if op == "COPY" and not rest.startswith("--from")]
    assert copies
    for rest in copies:
        *sources, _ = shlex.split(rest)
        for s in sources:
            assert (ROOT / s).exists(), f"Dockerfile copies {s}, which is not in the project"


def test_every_installed_package_is_copied_before_the_install():
    """``pip install .`` in the image installs what pyproject's package discovery finds in the copied
    tree: each top-level package must be copied, or the image lacks it (and gen_proto --check, which
    reads fmgs_wire/proto, fails)."""
    find = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]
    packages = {p.parent.name for p in ROOT.glob("*/__init__.py")}
    tops = {p for p in packages if any(fnmatch.fnmatchcase(p, pat) for pat in find["include"])}
    assert tops
    copied = set()
    for op, rest in _instructions():
        if op == "COPY" and not rest.startswith("--from"):
            copied |= {s.rstrip("/") for s in shlex.split(rest)[:-1]}
    assert tops <= copied, f"the Dockerfile does not copy {sorted(tops - copied)}"


def test_files_named_in_run_lines_exist():
    runs = " ".join(rest for op, rest in _instructions() if op == "RUN")
    for path in re.findall(r"(?:requirements|scripts)/[\w./-]+", runs):
        assert (ROOT / path).exists(), path
    # The pinned torch in the image is the CPU pin's version.
    pin = re.search(r"^torch==(\S+)", (ROOT / "requirements/cpu.txt").read_text(), re.M).group(1)
    assert f"torch=={pin}" in runs


def _args() -> dict[str, str]:
    """The Dockerfile's ARG defaults (global and per stage)."""
    out = {}
    for op, rest in _instructions():
        if op == "ARG":
            name, _, default = rest.partition("=")
            out.setdefault(name, default)
    return out


def test_entrypoint_and_healthcheck_are_real_commands(tmp_path):
    ins = dict(_instructions())
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    entry = json.loads(ins["ENTRYPOINT"])
    assert entry[0] in scripts and scripts[entry[0]] == "fmgs_server.cli:main"
    from fmgs_server.cli import build_parser, config_from_args

    # The build writes the flavour's settings file the entrypoint reads (device = the flavour).
    runs = " ".join(rest for op, rest in _instructions() if op == "RUN")
    written = re.search(r"printf '([^']*)' \"\$FLAVOUR\" > (\S+)", runs)
    assert written, "the build does not write the flavour's settings"
    template, path = written.groups()
    assert entry[entry.index("--config") + 1] == path
    assert any(op == "COPY" and rest.split()[-1] == path for op, rest in _runtime_stage())
    for flavour in ("cuda", "cpu"):
        toml = tmp_path / f"{flavour}.toml"
        toml.write_text(template.replace("%s", flavour).replace("\\n", "\n"))
        argv = [str(toml) if a == path else a for a in entry[1:]]
        cfg = config_from_args(build_parser().parse_args(argv))
        assert str(cfg.models) == "/models" and cfg.host == "0.0.0.0" and cfg.device == flavour
    health = json.loads(ins["HEALTHCHECK"].split("CMD", 1)[1].strip())
    assert health[0] in scripts
    from fmgs_client.cli import build_parser as client_parser

    c = client_parser().parse_args(health[1:])
    assert c.address == "127.0.0.1:50051"
    assert str(cfg.port) == c.address.rsplit(":", 1)[1]


def test_image_is_multi_stage_with_a_runtime_base():
    froms = [rest for op, rest in _instructions() if op == "FROM"]
    assert froms == ["${BUILD_BASE} AS build", "${RUNTIME_BASE}"]
    args = _args()
    # The CUDA bases stay the default; the CPU flavour passes Debian ones (scripts/image.sh).
    assert "cuda" in args["BUILD_BASE"] and "devel" in args["BUILD_BASE"]
    assert "cuda" in args["RUNTIME_BASE"] and "runtime" in args["RUNTIME_BASE"]
    assert args["FLAVOUR"] == "cuda"


def test_flavours_install_what_they_need():
    runs = " ".join(rest for op, rest in _instructions() if op == "RUN")
    # gsplat only for cuda, built from source (PyPI's wheel compiles with nvcc at run time, which the
    # runtime stage lacks), and the build fails unless its compiled module imports.
    cuda_only = r'if \[ "\$FLAVOUR" = cuda \]; then .*gsplat @ git\+\S+@v1\.5\.\d.*import gsplat\.csrc'
    assert re.search(cuda_only, runs)
    assert "cuda|cpu)" in runs, "an unknown FLAVOUR must stop the build"
    # torch from a mounted wheel folder when given, else the flavour's index.
    assert '--find-links "$TORCH_WHEELS" torch==' in runs and '--index-url "$TORCH_INDEX"' in runs
    # Every pip step trusts the mounted CA bundle when one is given.
    for step in (rest for op, rest in _instructions() if op == "RUN" and "pip install" in rest):
        assert 'export PIP_CERT="$PIP_CERT_FILE"' in step.split("pip install", 1)[0], step[:80]
    script = (ROOT / "scripts/image.sh").read_text()
    for arg in ("FLAVOUR", "BUILD_BASE", "RUNTIME_BASE", "TORCH_WHEELS", "TORCH_INDEX", "PIP_CERT_FILE"):
        assert f"--build-arg {arg}=" in script or f'--build-arg "{arg}=' in script, arg
        assert arg in _args(), f"scripts/image.sh passes {arg}, which the Dockerfile does not declare"


def _runtime_stage() -> list[tuple[str, str]]:
    ins = _instructions()
    last_from = max(i for i, (op, _) in enumerate(ins) if op == "FROM")
    return ins[last_from + 1 :]


def test_image_carries_ray_serve_for_the_cluster_deployment():
    """fmgs-server --ray and the KubeRay RayService (deploy/kuberay) run `ray start` in this image."""
    runs = " ".join(rest for op, rest in _instructions() if op == "RUN")
    assert "pip install -r requirements/cpu.txt" in runs
    extra = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]["ray"]
    pin = next(r for r in extra if r.startswith("ray[serve]=="))
    cpu = [ln.split("#")[0].strip() for ln in (ROOT / "requirements/cpu.txt").read_text().splitlines()]
    assert pin in cpu, f"the image's environment (requirements/cpu.txt) lacks the fmgs[ray] pin {pin}"
    # The virtual environment's bin (ray, fmgs-server) is on the runtime PATH, and wget is there for
    # KubeRay's default probes.
    runtime = _runtime_stage()
    env = " ".join(rest for op, rest in runtime if op == "ENV")
    assert re.search(r"PATH=/opt/venv/bin:", env)
    assert any(op == "COPY" and rest.split()[-2:] == ["/opt/venv", "/opt/venv"] for op, rest in runtime)
    apt = next(rest for op, rest in runtime if op == "RUN" and "apt-get install" in rest)
    assert "wget" in shlex.split(apt.split("apt-get install", 1)[1])


def test_image_serves_warm_with_admin_calls_closed_and_its_kernels_compiled():
    """The entrypoint preloads (health NOT_SERVING until warm) and names no admin token file (admin calls
    refused on 0.0.0.0); the build compiles the kernels into a NUMBA_CACHE_DIR the fmgs user can write."""
    from fmgs_server.cli import build_parser, config_from_args

    ins = _instructions()
    entry = json.loads(dict(ins)["ENTRYPOINT"])
    argv = [a for a in entry[1:] if a not in ("--config", "/etc/fmgs/image.toml")]
    cfg = config_from_args(build_parser().parse_args(argv))
    assert cfg.preload and cfg.admin_token_file is None and not cfg.admin_without_token
    stage = _runtime_stage()
    env = " ".join(rest for op, rest in stage if op == "ENV")
    cache = re.search(r"NUMBA_CACHE_DIR=(\S+)", env)
    assert cache, "the runtime stage sets no NUMBA_CACHE_DIR"
    runs = [rest for op, rest in stage if op == "RUN"]
    assert any("chown fmgs" in r and "NUMBA_CACHE_DIR" in r for r in runs), "the cache is not the user's"
    precompile = [r for r in runs if "--precompile" in r]
    assert precompile, "the build compiles no kernels"
    argv = shlex.split(precompile[0])
    assert argv[0] == entry[0]
    a = build_parser().parse_args(argv[1:])
    assert a.precompile and str(config_from_args(a).models) == "/models"
    users = [rest for op, rest in stage if op == "USER"]
    assert users and stage.index(("USER", users[-1])) < stage.index(("RUN", precompile[0])), "run as fmgs"
