"""CPU threads of a training run: torch intra-op and numba, set together for the run and restored after.

Both pools default to every core and spin while they wait, so on a machine whose cores other jobs already
use they oversubscribe: a train-gs run on a loaded 2-core machine made 0.26 steps/s with 2 threads and
2.6 with 1 (benchmarks/results/THREADS.md). ``auto`` therefore takes only the cores idle when the run starts.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from contextlib import contextmanager

import torch


def available_cores() -> int:
    """Cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS and Windows have no affinity call
        return os.cpu_count() or 1


def auto_threads() -> int:
    """The cores not busy at this moment (cores minus the whole part of the 1-minute load average), at
    least 1: idle, 2 threads beat 1 on the 2-core machine (10.4-10.7 steps/s against 6.5-8.2); under a
    load of 6-8 they were 10x slower."""
    cores = available_cores()
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):  # no load average (Windows): trust the core count
        load = 0.0
    return max(1, min(cores, cores - math.floor(load)))


@contextmanager
def thread_count(threads: int) -> Iterator[int]:
    """Run the block with ``threads`` torch and numba threads (0: ``auto_threads()``); yields the count
    in effect and restores the previous counts on exit."""
    import numba

    n = threads if threads > 0 else auto_threads()
    n_numba = min(n, numba.config.NUMBA_NUM_THREADS)  # numba cannot exceed its pool's launch size
    before = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(n)
    numba.set_num_threads(n_numba)
    try:
        yield n
    finally:
        torch.set_num_threads(before[0])
        numba.set_num_threads(before[1])
