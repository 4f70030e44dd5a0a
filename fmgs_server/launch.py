"""``fmgs-server`` as a subprocess: started on a free port, its address read from its first line (for
scripts, benchmarks and tests that need a server of their own, with its own process and memory)."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def start_subprocess(
    models: str | Path, *flags: str, via_fmgs: bool = False, stderr=subprocess.DEVNULL
) -> tuple[subprocess.Popen, str]:
    """Start ``fmgs-server --models MODELS --port 0 FLAGS`` (``fmgs serve ...`` with ``via_fmgs``); returns
    the process and its ``host:port`` once it serves. RuntimeError with what it printed if it does not."""
    entry = ["-m", "fmgs.cli", "serve"] if via_fmgs else ["-m", "fmgs_server.cli"]
    cmd = [sys.executable, *entry, "--models", str(models), "--port", "0", "--log-level", "WARNING", *flags]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=stderr, text=True, env=env)
    line = p.stdout.readline()
    if "serving" not in line:
        p.kill()
        err = p.stderr.read() if p.stderr else ""
        raise RuntimeError(f"fmgs-server did not start: {line!r} {err[-2000:]}")
    return p, line.rsplit(" ", 1)[1].strip().rstrip(")")  # the line ends with the address to connect to


@contextmanager
def subprocess_server(models: str | Path, *flags: str) -> Iterator[tuple[subprocess.Popen, str]]:
    """``start_subprocess`` for the duration of a ``with``; the process is killed at the end if alive."""
    p, address = start_subprocess(models, *flags)
    try:
        yield p, address
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(10)


def memory(pid: int) -> tuple[int, int]:
    """(resident bytes, peak resident bytes) of process ``pid`` (Linux ``/proc/PID/status``)."""
    fields = dict(
        line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line
    )
    return int(fields["VmRSS"].split()[0]) * 1024, int(fields["VmHWM"].split()[0]) * 1024


def reset_peak(pid: int) -> None:
    """Restart process ``pid``'s peak resident size from its current one (``/proc/PID/clear_refs``)."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")
