"""Optional compiled kernels (numba) for the query path's innermost loops.

The screen and the guided pose estimate spend most of their time in a few loops over (hypotheses x landmarks)
that numpy runs as ~15 separate passes over temporary arrays. With numba installed (the ``server`` extra) they
run as compiled loops that do the same floating-point operations in the same order (no ``fastmath``, so no
re-association and no fused multiply-add: the results are the same numbers, tested against the numpy path).
Without numba, or with ``RERADAR_JIT=0`` in the environment, the numpy path runs: same answers, slower.

One kernel is equal only up to float32 rounding: the Cen 2018 detector (``landmarks.cen2018_kernels``), whose
vectorised path rests on OpenCV's convolution and exp, which no compiled loop reproduces bit for bit; a keypoint
differs only where the response lies within ~1e-6 of the threshold (24 of 907,254 on simulated scans, none of
35,093 on the real Oxford scans: ``benchmarks/compare_detectors.py``).

Compiled code is cached on disk (``cache=True``: next to the sources, or in ``NUMBA_CACHE_DIR`` - the image
sets ``/data/cache/numba`` - or the user's cache folder when the sources are read-only), so only the first
process on a machine pays the compilation (~1-3 s per kernel); every ``Localizer`` compiles or loads them
when it is made (``matching.kernels.warm_up``; the service makes one per map at start-up), never in a query.
Kernels release the GIL (``nogil``), so a threaded server runs them in parallel.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any, TypeVar, cast

__all__ = ["jit_enabled", "njit"]

_F = TypeVar("_F", bound=Callable[..., Any])

_numba: Any
try:  # numba is optional: the ``server`` extra installs it, a library user may not have it
    import numba as _numba
except ImportError:  # pragma: no cover - exercised where numba is absent
    _numba = None


def jit_enabled() -> bool:
    """Whether the compiled kernels run: numba is importable and ``RERADAR_JIT`` is not ``0`` (read at each
    call, so tests can compare both paths in one process)."""
    return _numba is not None and os.environ.get("RERADAR_JIT", "1") != "0"


def njit(fn: _F | None = None, *, fastmath: bool | set[str] = False) -> Any:
    """``numba.njit(cache=True, nogil=True)`` when numba is installed, else ``fn`` unchanged (never called
    then: callers check ``jit_enabled()`` first and take the numpy path). Used bare (``@njit``) or with
    ``fastmath`` flags (``@njit(fastmath={"reassoc"})``: only where a kernel documents why its sums may be
    re-associated)."""
    if fn is None:
        return lambda f: njit(f, fastmath=fastmath)
    if _numba is None:  # pragma: no cover
        return fn
    try:
        return cast(_F, _numba.njit(cache=True, nogil=True, fastmath=fastmath)(fn))
    except RuntimeError:  # pragma: no cover - no writable cache folder: compile in every process instead
        return cast(_F, _numba.njit(nogil=True, fastmath=fastmath)(fn))
