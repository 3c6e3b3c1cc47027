"""Seeded k-means with k-means++ initialisation (no scikit-learn here): vocabularies for RadVLAD and NetVLAD.

k-means++ seeding: D. Arthur and S. Vassilvitskii, "k-means++: The advantages of careful seeding", SODA 2007.

``kmeans`` runs a fixed number of FAISS Lloyd iterations on a subsample (the fast variant).
``kmeans_to_convergence`` is what the OORD benchmark code runs (github.com/mttgdd/oord-dataset at
f04683fb68d15f042395de528c92064dbfc4bc30, ``src/radvlad.py`` ``do_cluster`` and
``jobs/test_resnet18_netvlad.py``: ``sklearn.cluster.KMeans(init='k-means++', tol=1e-4, n_init=1)`` on every
descriptor): scikit-learn's greedy k-means++ seeding (``2 + int(ln k)`` candidates per centre, the one that
lowers the potential most is kept), then Lloyd iterations on all points until the squared centre shift is at
most ``tol`` times the mean per-dimension variance of the data, or 300 iterations (scikit-learn's defaults).
The reference leaves the seed unset; ours is explicit.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse

from reradar_core.errors import ConfigError

__all__ = ["kmeans_plus_plus_init", "kmeans", "greedy_kmeans_plus_plus_init", "kmeans_to_convergence"]


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


def _sq_dists(x: np.ndarray, x_sq: np.ndarray, centres: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """(N, K) float32 squared Euclidean distances (clipped at 0), computed in chunks of points."""
    c = np.ascontiguousarray(centres, dtype=np.float32)
    c_sq = (c * c).sum(1)
    out = np.empty((x.shape[0], c.shape[0]), dtype=np.float32)
    for s in range(0, x.shape[0], chunk):
        d = x_sq[s : s + chunk, None] - 2.0 * (x[s : s + chunk] @ c.T) + c_sq[None]
        out[s : s + chunk] = np.maximum(d, 0.0)
    return out


def greedy_kmeans_plus_plus_init(x: np.ndarray, k: int, seed: int = 0) -> np.ndarray:
    """scikit-learn's greedy k-means++: (N, D) points -> (k, D) float32 initial centres.

    Each new centre is the best of ``2 + int(ln k)`` candidates drawn with probability proportional to the
    squared distance to the nearest chosen centre (best = lowest total squared distance afterwards).
    """
    x = np.ascontiguousarray(x, dtype=np.float32)
    n = x.shape[0]
    if n < k:
        raise ConfigError(f"k-means needs at least k={k} points, got {n}; use a larger reference run")
    rng = np.random.default_rng(seed)
    trials = 2 + int(np.log(k))
    x_sq = (x * x).sum(1)
    centres = np.empty((k, x.shape[1]), dtype=np.float32)
    centres[0] = x[rng.integers(n)]
    closest = _sq_dists(x, x_sq, centres[:1])[:, 0].astype(np.float64)
    for i in range(1, k):
        total = float(closest.sum())
        if total <= 0:  # every point sits on a centre already: any point will do
            cand = rng.integers(n, size=trials)
        else:
            cand = np.searchsorted(np.cumsum(closest), rng.random(trials) * total)
            cand = np.minimum(cand, n - 1)
        d_cand = _sq_dists(x, x_sq, x[cand]).astype(np.float64)  # (N, trials)
        new_closest = np.minimum(closest[:, None], d_cand)
        best = int(np.argmin(new_closest.sum(0)))
        centres[i] = x[cand[best]]
        closest = new_closest[:, best]
    return centres


def kmeans_to_convergence(x: np.ndarray, k: int, seed: int = 0, tol: float = 1e-4,
                          max_iter: int = 300) -> np.ndarray:
    """Greedy k-means++ then Lloyd to convergence on every point: (N, D) -> (k, D) float32 centres.

    Stops when the summed squared centre shift is ``<= tol * mean(var(x, axis=0))`` (scikit-learn's
    criterion) or after ``max_iter`` iterations. An empty cluster takes the point farthest from its centre.
    """
    x = np.ascontiguousarray(x, dtype=np.float32)
    n, dim = x.shape
    centres = greedy_kmeans_plus_plus_init(x, k, seed)
    tol_abs = tol * float(np.mean(np.var(x.astype(np.float64), axis=0)))
    x_sq = (x * x).sum(1)
    for _ in range(max_iter):
        d2 = _sq_dists(x, x_sq, centres)
        labels = np.argmin(d2, axis=1)
        counts = np.bincount(labels, minlength=k)
        onehot = sparse.csr_matrix((np.ones(n, np.float32), (labels, np.arange(n))), shape=(k, n))
        sums = np.asarray(onehot @ x, dtype=np.float64)
        new = centres.astype(np.float64).copy()
        full = counts > 0
        new[full] = sums[full] / counts[full, None]
        if not np.all(full):  # relocate empty clusters to the worst-fitted points
            far = np.argsort(-d2[np.arange(n), labels])
            for j, idx in zip(np.flatnonzero(~full), far, strict=False):
                new[j] = x[idx]
        shift = float(((new - centres) ** 2).sum())
        centres = new.astype(np.float32)
        if shift <= tol_abs:
            break
    return centres
