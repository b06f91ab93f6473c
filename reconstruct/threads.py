"""Thread pools sized by the program, not by the user's shell.

The nets and matrices of one fit are small: BLAS, OpenMP and torch threads only contend with
each other and with the other fitting process. Measured (issue 17): a 12-view
``scanstation scan`` took 416 s in a plain shell and 148 s with OMP_NUM_THREADS=1
OPENBLAS_NUM_THREADS=1. `limit_threads` sets every pool of this process (numpy's and scipy's
OpenBLAS, OpenMP, torch when it is loaded) to a share of the machine's cores; worker processes
call it once at start, and training runs inside `single_threaded`.
"""

from __future__ import annotations

import contextlib
import os
import sys

from threadpoolctl import threadpool_limits

_GLOBAL = None  # the process-wide limits, kept alive


def available_cores() -> int:
    """Cores this process may run on (its affinity mask; cgroup CPU quotas are not read)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def limit_threads(processes: int = 1) -> int:
    """Limit this process's thread pools to its share of the cores when ``processes`` fit side
    by side (at least 1). Returns the thread count set."""
    global _GLOBAL
    threads = max(1, available_cores() // max(1, int(processes)))
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[name] = str(threads)  # read by the libraries that are loaded later
    _GLOBAL = threadpool_limits(limits=threads)  # the ones loaded already
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(threads)
    return threads


@contextlib.contextmanager
def single_threaded():
    """BLAS and OpenMP pools at one thread inside the block (restored after)."""
    with threadpool_limits(limits=1):
        yield
