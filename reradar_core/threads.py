"""Limit the BLAS thread pools at run time (``threadpoolctl``).

numpy, scipy and opencv-python-headless each bundle their own OpenBLAS. Once scipy.linalg is loaded next to
numpy (e2cnn and the simulator import it), numpy's small matrix products - descriptor matching, 1200 x 400 x
32 - take ~16 ms instead of ~0.4 ms on a 2-core machine (measured), the pools fighting for the cores.
Serving one request at a time gains nothing from BLAS threads at these sizes, so the service limits every
loaded BLAS to one thread at start-up (``RERADAR_BLAS_THREADS``), and ``reradar bench --threads N`` limits them
to N once its methods are loaded. ``OPENBLAS_NUM_THREADS=1`` in the environment before Python starts has the
same effect.
"""

from __future__ import annotations

import logging

import numpy as np
from threadpoolctl import threadpool_info, threadpool_limits

__all__ = ["limit_blas_threads", "limit_malloc_arenas"]

logger = logging.getLogger(__name__)


def limit_blas_threads(n: int) -> bool:
    """Set the threads of every BLAS library loaded in the process (numpy's, scipy's, opencv's) to ``n``;
    returns False when none is loaded."""
    np.ones((2, 2)) @ np.ones((2, 2))  # make sure numpy's BLAS is loaded
    # threadpool_limits used as a plain call (not a context manager) keeps the limit for the process' life
    threadpool_limits(limits=n, user_api="blas")
    libs = [info for info in threadpool_info() if info.get("user_api") == "blas"]
    for info in libs:
        logger.debug("BLAS %s (%s) threads: %s", info.get("internal_api"), info.get("filepath"),
                     info.get("num_threads"))
    return bool(libs)


#: glibc's ``mallopt`` parameter number of M_ARENA_MAX (malloc.h)
_M_ARENA_MAX = -8


def limit_malloc_arenas(n: int) -> bool:
    """Cap glibc's malloc arenas at ``n`` (``MALLOC_ARENA_MAX``; glibc's default is 8 per core), so the
    threads of a server (request thread pool, BLAS, FAISS) allocate from a few shared heaps instead of one
    growing heap each. Measured on a 2-worker service (docs/BENCHMARKS.md): private memory 40-60 MB lower
    with 2, at the same throughput. Call it before the threads start; returns False where it does not apply (no
    glibc)."""
    try:
        import ctypes

        return bool(ctypes.CDLL("libc.so.6").mallopt(_M_ARENA_MAX, int(n)))
    except (OSError, AttributeError):
        return False
