"""Limit the OpenBLAS thread pools at run time.

numpy, scipy and opencv-python-headless each bundle their own OpenBLAS. Once scipy.linalg is loaded next to
numpy (e2cnn and the simulator import it), numpy's small matrix products - descriptor matching, 1200 x 400 x
32 - take ~16 ms instead of ~0.4 ms on this 2-core machine (measured), the pools fighting for the cores.
Serving one request at a time gains nothing from BLAS threads at these sizes, so the service limits every
loaded OpenBLAS to one thread at start-up (``RERADAR_BLAS_THREADS``). ``OPENBLAS_NUM_THREADS=1`` in the
environment before Python starts has the same effect.
"""

from __future__ import annotations

import ctypes
import logging

import numpy as np

__all__ = ["limit_blas_threads"]

logger = logging.getLogger(__name__)

_SETTERS = ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads", "openblas_set_num_threads64_",
            "openblas_set_num_threads")
# numpy, scipy and opencv each bundle an OpenBLAS; all three pools are limited


def _openblas_paths() -> list[str]:
    np.ones((2, 2)) @ np.ones((2, 2))  # make sure the BLAS library is loaded
    paths: list[str] = []
    try:
        with open("/proc/self/maps") as fh:
            for line in fh:
                path = line.split()[-1] if len(line.split()) >= 6 else ""
                if "openblas" in path.lower():
                    if path not in paths:
                        paths.append(path)
    except OSError:  # not Linux
        return []
    return paths


def limit_blas_threads(n: int) -> bool:
    """Set the threads of every OpenBLAS loaded in the process (numpy's, scipy's, opencv's) to ``n``;
    returns False when none could be found."""
    done = False
    for path in _openblas_paths():
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for name in _SETTERS:
            fn = getattr(lib, name, None)
            if fn is not None:
                fn(ctypes.c_int(n))
                logger.debug("BLAS threads set to %d via %s in %s", n, name, path)
                done = True
                break
    if not done:
        logger.debug("no OpenBLAS found; BLAS threads unchanged")
    return done
