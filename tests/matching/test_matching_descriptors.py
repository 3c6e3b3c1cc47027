"""Mutual nearest-neighbour cosine matching recovers a known permutation; ratio test; empty inputs."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.errors import ModelMismatchError
from reradar_core.matching import cosine_similarity, match_descriptors


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def test_recovers_known_permutation_with_noise_float16():
    rng = np.random.default_rng(0)
    a = _unit(rng.normal(size=(200, 32)))
    perm = rng.permutation(200)
    b = _unit(a[perm] + 0.05 * rng.normal(size=a.shape))  # b[k] is a noisy copy of a[perm[k]]
    matches = match_descriptors(a.astype(np.float16), b.astype(np.float16))
    assert matches.dtype == np.int64 and matches.shape == (200, 2)
    inv = np.argsort(perm)  # a[i] is at b[inv[i]]
    np.testing.assert_array_equal(matches[:, 0], np.arange(200))
    np.testing.assert_array_equal(matches[:, 1], inv[matches[:, 0]])


def test_mutual_check_drops_one_sided_matches():
    a = np.array([[1.0, 0.0], [0.9, 0.1]])
    b = np.array([[1.0, 0.0], [0.0, 1.0]])
    # both a rows prefer b[0]; b[0] prefers a[0]; b[1]'s best is a[1] but a[1]'s best is b[0]
    np.testing.assert_array_equal(match_descriptors(a, b), [[0, 0]])
    np.testing.assert_array_equal(match_descriptors(a, b, mutual=False), [[0, 0], [1, 0]])


def test_ratio_test_rejects_ambiguous():
    a = np.array([[1.0, 0.02, 0.0], [0.0, 1.0, 0.0]])
    b = np.array([[1.0, 0.0, 0.0], [1.0, 0.045, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    # a[0] lies almost midway between b[0] and b[1]: ambiguous; a[1] equals b[2]: distance 0, clear
    plain = match_descriptors(a, b, mutual=False)
    assert plain.tolist() == [[0, 0], [1, 2]]
    np.testing.assert_array_equal(match_descriptors(a, b, ratio=0.8, mutual=False), [[1, 2]])


def test_unnormalised_and_zero_descriptors():
    a = np.array([[3.0, 0.0], [0.0, 0.0]])
    b = np.array([[0.0, 5.0], [2.0, 0.1]])
    sim = cosine_similarity(a, b)
    assert sim.dtype == np.float32
    np.testing.assert_allclose(sim[0], [0.0, 2.0 / np.hypot(2.0, 0.1)], rtol=1e-6)
    np.testing.assert_array_equal(sim[1], [0.0, 0.0])
    assert match_descriptors(a, b)[0].tolist() == [0, 1]


def test_empty_inputs():
    assert match_descriptors(np.zeros((0, 8)), np.ones((5, 8))).shape == (0, 2)
    assert match_descriptors(np.ones((5, 8)), np.zeros((0, 8)), ratio=0.8).shape == (0, 2)
    assert match_descriptors(np.zeros((0, 8), np.float16), np.zeros((0, 8), np.float16)).dtype == np.int64
    # one candidate only: ratio test cannot apply, the nearest neighbour is kept
    assert match_descriptors(np.ones((1, 4)), np.ones((1, 4)), ratio=0.8).tolist() == [[0, 0]]


def test_bad_inputs():
    with pytest.raises(ModelMismatchError, match="channels"):
        match_descriptors(np.ones((3, 8)), np.ones((3, 16)))
    with pytest.raises(ValueError, match="2-D"):
        match_descriptors(np.ones(8), np.ones((3, 8)))
    with pytest.raises(ValueError, match="ratio"):
        match_descriptors(np.ones((3, 8)), np.ones((3, 8)), ratio=1.5)
    bad = np.ones((3, 8))
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        match_descriptors(bad, np.ones((3, 8)))
