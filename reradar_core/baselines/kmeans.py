"""Seeded k-means with k-means++ initialisation (no scikit-learn here): vocabularies for RadVLAD and NetVLAD.

k-means++ seeding: D. Arthur and S. Vassilvitskii, "k-means++: The advantages of careful seeding", SODA 2007.
Lloyd iterations run with FAISS (exact L2), starting from the k-means++ centres.
"""

from __future__ import annotations

import numpy as np

from reradar_core.errors import ConfigError

__all__ = ["kmeans_plus_plus_init", "kmeans"]


def kmeans_plus_plus_init(x: np.ndarray, k: int, seed: int = 0) -> np.ndarray:
    """k-means++ seeding: (N, D) float32 points -> (k, D) float32 initial centres (deterministic for a seed)."""
    x = np.ascontiguousarray(x, dtype=np.float32)
    n = x.shape[0]
    if n < k:
        raise ConfigError(f"k-means needs at least k={k} points, got {n}; use a larger reference run")
    rng = np.random.default_rng(seed)
    centres = np.empty((k, x.shape[1]), dtype=np.float32)
    centres[0] = x[rng.integers(n)]
    sq = (x * x).sum(1)
    d2 = np.maximum(sq - 2.0 * x @ centres[0] + float(centres[0] @ centres[0]), 0.0)
    for i in range(1, k):
        total = float(d2.sum())
        j = int(rng.integers(n)) if total <= 0 else int(rng.choice(n, p=d2 / total))
        centres[i] = x[j]
        d2 = np.minimum(d2, np.maximum(sq - 2.0 * x @ centres[i] + float(centres[i] @ centres[i]), 0.0))
    return centres


def kmeans(x: np.ndarray, k: int, iterations: int = 20, seed: int = 0, max_points: int = 50_000) -> np.ndarray:
    """k-means++ then Lloyd: (N, D) points -> (k, D) float32 centres.

    At most ``max_points`` points (a seeded random subset) are used, to bound time on long reference runs.
    """
    import faiss

    x = np.ascontiguousarray(x, dtype=np.float32)
    if x.shape[0] > max_points:
        x = x[np.random.default_rng(seed).choice(x.shape[0], max_points, replace=False)]
    init = kmeans_plus_plus_init(x, k, seed)
    km = faiss.Kmeans(x.shape[1], k, niter=iterations, seed=seed, verbose=False, spherical=False,
                      max_points_per_centroid=max(1, x.shape[0] // k + 1))
    km.train(x, init_centroids=init)
    return np.asarray(km.centroids, dtype=np.float32).reshape(k, x.shape[1])
