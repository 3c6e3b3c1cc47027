"""Learned whitening of raw NetVLAD vectors from matching pairs (Radenović et al., "Fine-tuning CNN image
retrieval with no human annotation", TPAMI 2018, Sec. 3.4; after Mikolajczyk & Matas, ICCV 2007).

The projection that turns the raw (K*C) NetVLAD vector into the global descriptor starts as PCA-whitening
(``DescriptorNet.init_whitening``) and is trained end to end. PCA-whitening amplifies every low-variance
direction alike, including those along which two scans of the *same* place differ (another traversal, weather,
a heading between the 90° steps the network is exactly invariant to). Learned whitening instead:

1. whitens by the covariance of the differences of matching pairs, ``C_S = mean((x_a - x_b)(x_a - x_b)^T)``
   (shrunk towards a multiple of the identity by ``shrinkage``, so that 512 dimensions are well conditioned
   with a few thousand pairs): directions along which matching scans differ are shrunk, and
2. rotates onto the principal axes of all training vectors in that whitened space, keeping the ``dim``
   directions of largest variance (those that separate places).

``P = R_dim C_S^{-1/2}``, ``proj(x) = P (x - mu)`` with ``mu`` the mean of the pair vectors; the descriptor is
``proj(x)`` L2-normalised. It is one linear map, so it replaces the weights and bias of the network's projection
layer (same shapes): no change to the network, the exported file format, or inference time.
"""

from __future__ import annotations

import numpy as np

from reradar_core.errors import ConfigError

__all__ = ["learned_whitening", "matching_pairs"]


def matching_pairs(xy: np.ndarray, sequence: np.ndarray, group: np.ndarray, radius_m: float) -> np.ndarray:
    """Each scan with its nearest scan of *another* sequence of the same world group within ``radius_m``.

    Args:
        xy: (N, 2) float scan positions, metres (each group's world frame).
        sequence: (N,) int sequence of each scan; group: (N,) int world group of each scan.
        radius_m: largest distance of a matching pair, metres.

    Returns:
        (P, 2) int64 index pairs (a, b), a in increasing order; scans without a match are left out.
    """
    from scipy.spatial import cKDTree

    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    sequence, group = np.asarray(sequence).reshape(-1), np.asarray(group).reshape(-1)
    out: list[np.ndarray] = []
    for g in np.unique(group):
        for s in np.unique(sequence[group == g]):
            own = np.flatnonzero((group == g) & (sequence == s))
            other = np.flatnonzero((group == g) & (sequence != s))  # another traversal of the same world
            if len(other) == 0:
                continue
            dist, nn = cKDTree(xy[other]).query(xy[own], distance_upper_bound=radius_m)
            ok = np.isfinite(dist)
            out.append(np.stack([own[ok], other[nn[ok]]], axis=1))
    if not out:
        return np.zeros((0, 2), np.int64)
    pairs = np.concatenate(out).astype(np.int64)
    return pairs[np.argsort(pairs[:, 0], kind="stable")]


def learned_whitening(x_a: np.ndarray, x_b: np.ndarray, x_all: np.ndarray, dim: int,
                      shrinkage: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Fit the learned-whitening projection (module docstring).

    Args:
        x_a, x_b: (P, D) raw descriptors of matching pairs (row i of both: the same place), any float dtype.
        x_all: (N, D) raw descriptors of the training scans (their spread defines the kept directions).
        dim: output dimension (<= D).
        shrinkage: weight in [0, 1) of the identity (scaled to ``C_S``'s mean eigenvalue) mixed into ``C_S``.
            Default 0.1: on the ``train-target-boreas`` validation tails (the descriptor's held-out part of
            the training split) 0.0 / 0.1 / 0.3 gave Recall@1 88.3 / 91.0 / 89.2 and 82.0 / 88.3 / 83.8 %
            (docs/MODEL.md, "Learned whitening").

    Returns:
        ``(weight, bias)``: (dim, D) and (dim,) float64 with ``proj(x) = weight @ x + bias``. Eigenvector signs
        are fixed (largest-magnitude entry positive), so the result does not depend on the LAPACK build's sign
        choice.

    Raises:
        ConfigError: mismatched shapes, too few pairs, ``dim`` larger than D or ``shrinkage`` outside [0, 1).
    """
    a = np.asarray(x_a, np.float64)
    b = np.asarray(x_b, np.float64)
    x = np.asarray(x_all, np.float64)
    if a.ndim != 2 or a.shape != b.shape or x.ndim != 2 or x.shape[1] != a.shape[1]:
        raise ConfigError(f"pair arrays {a.shape} / {b.shape} and training array {x.shape} do not match")
    d = a.shape[1]
    if not 1 <= dim <= d:
        raise ConfigError(f"learned whitening needs 1 <= dim <= {d}, got {dim}")
    if not 0.0 <= shrinkage < 1.0:
        raise ConfigError(f"shrinkage must be in [0, 1), got {shrinkage}")
    if len(a) < 2:
        raise ConfigError(f"learned whitening needs matching pairs; got {len(a)}")
    mu = np.concatenate([a, b]).mean(axis=0)
    diff = a - b
    c_s = diff.T @ diff / len(diff)
    c_s = (1.0 - shrinkage) * c_s + shrinkage * (np.trace(c_s) / d) * np.eye(d)
    lam, vec = np.linalg.eigh(c_s)
    lam = np.maximum(lam, lam.max() * 1e-9)  # only with shrinkage 0 and rank-deficient pairs
    p_w = (vec / np.sqrt(lam)) @ vec.T  # C_S^{-1/2}, symmetric
    xw = (x - mu) @ p_w.T
    c_d = xw.T @ xw / len(xw)
    lam_d, vec_d = np.linalg.eigh(c_d)
    keep = vec_d[:, np.argsort(-lam_d, kind="stable")[:dim]]  # (D, dim)
    keep *= np.where(keep[np.argmax(np.abs(keep), axis=0), np.arange(dim)] < 0, -1.0, 1.0)
    weight = keep.T @ p_w
    return weight, -(weight @ mu)
