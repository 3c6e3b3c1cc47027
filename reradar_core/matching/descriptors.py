"""Nearest-neighbour matching of local descriptors by cosine similarity (mutual check, optional ratio test)."""

from __future__ import annotations

import numpy as np

from reradar_core.errors import ModelMismatchError

__all__ = ["match_descriptors", "cosine_similarity"]


def _normalise_rows(desc: np.ndarray, name: str) -> np.ndarray:
    d = np.asarray(desc)
    if d.ndim != 2:
        raise ValueError(f"{name} must be a 2-D (N, C) descriptor array, got shape {d.shape}")
    d = d.astype(np.float32, copy=True)
    if not np.all(np.isfinite(d)):
        raise ValueError(f"{name} contains NaN or infinite values")
    norms = np.linalg.norm(d, axis=1, keepdims=True)
    np.divide(d, norms, out=d, where=norms > 0)
    return d


def cosine_similarity(desc_a: np.ndarray, desc_b: np.ndarray) -> np.ndarray:
    """(N, C) x (M, C) descriptors (any float dtype) -> (N, M) float32 cosine similarity in [-1, 1].

    Rows are L2-normalised in float32 first (float16 descriptors are widened, never multiplied in float16);
    an all-zero row has similarity 0 with everything.
    """
    a = _normalise_rows(desc_a, "desc_a")
    b = _normalise_rows(desc_b, "desc_b")
    if a.shape[1] != b.shape[1]:
        raise ModelMismatchError(f"descriptor sizes differ: desc_a has {a.shape[1]} channels, desc_b {b.shape[1]}")
    return a @ b.T


def match_descriptors(
    desc_a: np.ndarray,
    desc_b: np.ndarray,
    ratio: float | None = None,
    mutual: bool = True,
) -> np.ndarray:
    """Match two descriptor sets by nearest neighbour in cosine similarity.

    Args:
        desc_a: (N, C) descriptors of set a (float16/float32; L2-normalised or not).
        desc_b: (M, C) descriptors of set b.
        ratio: Lowe ratio test on Euclidean distances of the unit vectors, d = sqrt(2 - 2 cos): keep a's
            match only if d(best) < ratio * d(second best). ``None`` disables it (needs M >= 2 to apply).
        mutual: keep only pairs that are each other's nearest neighbour.

    Returns:
        (K, 2) int64 index pairs (i into desc_a, j into desc_b), sorted by i; empty (0, 2) if either set is
        empty.

    Raises:
        ModelMismatchError: the two sets have different channel counts (descriptors from different models).
        ValueError: wrong shapes, non-finite values or ratio outside (0, 1].
    """
    if ratio is not None and not (0.0 < ratio <= 1.0):
        raise ValueError(f"ratio must be in (0, 1], got {ratio}")
    sim = cosine_similarity(desc_a, desc_b)
    n, m = sim.shape
    if n == 0 or m == 0:
        return np.zeros((0, 2), dtype=np.int64)
    idx_a = np.arange(n)
    nn_ab = np.argmax(sim, axis=1)
    keep = np.ones(n, dtype=bool)
    if mutual:
        nn_ba = np.argmax(sim, axis=0)
        keep &= nn_ba[nn_ab] == idx_a
    if ratio is not None and m >= 2:
        top2 = -np.partition(-sim, 1, axis=1)[:, :2]  # (N, 2): best and second-best similarity
        dist = np.sqrt(np.maximum(2.0 - 2.0 * top2, 0.0))
        keep &= dist[:, 0] < ratio * dist[:, 1]
    return np.stack([idx_a[keep], nn_ab[keep]], axis=1).astype(np.int64)
