"""Redirect what native libraries write to the process's stdout and stderr (file descriptors 1 and 2)."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def output_to(path: Path) -> Iterator[None]:
    """Append what native code (COLMAP's glog lines, ~170 an SfM run) writes to stdout and stderr to
    ``path`` for the block. Process-wide: not for servers with other threads writing."""
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        saved = os.dup(1), os.dup(2)
    except OSError:  # no standard streams (a daemon): nothing to keep clean
        yield
        return
    try:
        with open(path, "ab") as f:
            os.dup2(f.fileno(), 1)
            os.dup2(f.fileno(), 2)
            yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])
