"""The service's thread limits: BLAS (``reradar_core.threads.limit_blas_threads``, also used by ``reradar bench``)
and torch, set together before a model loads (``limit_threads``: the API process and a build worker)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from reradar_core.threads import limit_blas_threads

if TYPE_CHECKING:
    from service.core.config import Settings

__all__ = ["limit_blas_threads", "limit_threads"]


def limit_threads(cfg: Settings) -> None:
    """Set torch's and BLAS' thread counts (RERADAR_TORCH_THREADS, RERADAR_BLAS_THREADS) before the model loads:
    its ONNX Runtime session is created at torch's thread count (``OnnxNetwork``); loaded at another count, the
    first request would create a second session."""
    import torch

    torch.set_num_threads(cfg.torch_threads)
    limit_blas_threads(cfg.blas_threads)
