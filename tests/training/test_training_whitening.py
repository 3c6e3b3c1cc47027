"""Learned whitening (``training.whitening``): matching pairs by position, and a projection that keeps what
separates places and drops what differs between two scans of one place."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.errors import ConfigError
from reradar_core.training.whitening import learned_whitening, matching_pairs


def test_matching_pairs_take_the_nearest_scan_of_another_traversal_within_the_radius() -> None:
    # two traversals of one world (group 0) and one of another world (group 1) at the same coordinates
    xy = np.array([[0.0, 0], [10, 0], [50, 0],     # traversal 0, group 0
                   [1.0, 0], [12, 0], [90, 0],     # traversal 1, group 0
                   [0.0, 0], [10, 0]])             # traversal 2, group 1: another world, never a match
    seq = np.array([0, 0, 0, 1, 1, 1, 2, 2])
    group = np.array([0, 0, 0, 0, 0, 0, 1, 1])
    pairs = matching_pairs(xy, seq, group, radius_m=5.0)
    assert pairs.tolist() == [[0, 3], [1, 4], [3, 0], [4, 1]]  # 50 m and 90 m have no partner; no same-traversal
    assert matching_pairs(xy, np.zeros(8, int), group, 5.0).shape == (0, 2)  # one traversal: nothing


def test_learned_whitening_drops_the_direction_along_which_one_place_varies() -> None:
    rng = np.random.default_rng(0)
    n_places, d = 200, 6
    place = rng.normal(size=(n_places, 2))  # what tells places apart: 2 directions, unit spread

    def scans() -> np.ndarray:  # one traversal: place signal + a large per-scan nuisance + small noise
        x = np.zeros((n_places, d))
        x[:, :2] = place
        x[:, 2] = rng.normal(scale=5.0, size=n_places)  # e.g. weather: large, different on every pass
        x[:, 3:] = rng.normal(scale=0.05, size=(n_places, d - 3))
        return x + 3.0  # a common offset (the mean is removed)

    a, b = scans(), scans()
    weight, bias = learned_whitening(a, b, np.concatenate([a, b]), dim=2, shrinkage=0.0)
    assert weight.shape == (2, d) and bias.shape == (2,)
    # the kept directions carry the place signal, not the nuisance: dimension 2 gets almost no weight
    assert np.abs(weight[:, 2]).max() < 0.05 * np.abs(weight[:, :2]).max()

    def retrieve(pa: np.ndarray, pb: np.ndarray) -> float:
        pa = pa / np.linalg.norm(pa, axis=1, keepdims=True)
        pb = pb / np.linalg.norm(pb, axis=1, keepdims=True)
        return float(np.mean(np.argmax(pa @ pb.T, axis=1) == np.arange(n_places)))

    # new traversals of the same places: the learned projection finds them, plain PCA onto 2 axes does not
    c, e = scans(), scans()
    learned = retrieve(c @ weight.T + bias, e @ weight.T + bias)
    x = np.concatenate([a, b]) - np.concatenate([a, b]).mean(0)
    pca = np.linalg.eigh(x.T @ x)[1][:, ::-1][:, :2]  # the two largest-variance axes (nuisance first)
    plain = retrieve((c - 3.0) @ pca, (e - 3.0) @ pca)
    assert learned > 0.9 and plain < 0.3
    # deterministic
    w2, b2 = learned_whitening(a, b, np.concatenate([a, b]), dim=2, shrinkage=0.0)
    np.testing.assert_array_equal(w2, weight)
    np.testing.assert_array_equal(b2, bias)


def test_learned_whitening_refuses_bad_arguments() -> None:
    x = np.ones((4, 3))
    with pytest.raises(ConfigError):
        learned_whitening(x, x[:3], x, 2)
    with pytest.raises(ConfigError):
        learned_whitening(x, x, x, 4)
    with pytest.raises(ConfigError):
        learned_whitening(x, x, x, 2, shrinkage=1.0)
    with pytest.raises(ConfigError):
        learned_whitening(x[:1], x[:1], x, 2)
