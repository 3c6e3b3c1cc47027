"""The service's BLAS thread limit: ``reradar_core.threads.limit_blas_threads`` (also used by ``reradar bench``)."""

from __future__ import annotations

from reradar_core.threads import limit_blas_threads

__all__ = ["limit_blas_threads"]
