"""k-means to convergence (the OORD reference's scikit-learn KMeans semantics)."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.baselines.kmeans import greedy_kmeans_plus_plus_init, kmeans_to_convergence
from reradar_core.errors import ConfigError


def _blobs(seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    true = np.array([[0, 0], [20, 0], [0, 20], [20, 20]], np.float32)
    labels = np.repeat(np.arange(4), 200)
    x = (true[labels] + rng.normal(scale=1.0, size=(800, 2))).astype(np.float32)
    return x, labels, true


def test_converged_centres_are_the_cluster_means():
    """At convergence every centre is exactly the mean of its points (a fixed point of Lloyd)."""
    x, labels, true = _blobs()
    c = kmeans_to_convergence(x, 4, seed=0, tol=0.0)
    order = np.argmin(np.linalg.norm(c[:, None] - true[None], axis=-1), axis=0)
    means = np.stack([x[labels == i].mean(0) for i in range(4)])
    assert np.allclose(c[order], means, atol=1e-4)


def test_greedy_seeding_is_deterministic_and_picks_data_points():
    x, _, _ = _blobs()
    a = greedy_kmeans_plus_plus_init(x, 4, seed=3)
    assert np.array_equal(a, greedy_kmeans_plus_plus_init(x, 4, seed=3))
    assert all(np.any(np.all(x == row, axis=1)) for row in a)
    # D^2 sampling with 2 + ln 4 trials puts the four seeds in four different blobs
    assert len({(int(r[0] > 10), int(r[1] > 10)) for r in a}) == 4


def test_too_few_points_is_a_config_error():
    with pytest.raises(ConfigError, match="at least k"):
        kmeans_to_convergence(np.zeros((3, 2), np.float32), 4)
