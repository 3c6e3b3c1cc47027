"""SE(2) identities on random poses, angle wrapping, point transforms."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.geometry.se2 import (
    angle_diff,
    compose,
    inverse,
    matrix_to_se2,
    relative_pose,
    se2_to_matrix,
    transform_points,
    wrap_angle,
)


@pytest.fixture
def poses():
    rng = np.random.default_rng(7)
    n = 50
    return [np.column_stack([rng.uniform(-100, 100, (n, 2)), rng.uniform(-np.pi, np.pi, n)]) for _ in range(3)]


def _assert_pose_close(a, b, atol=1e-9):
    np.testing.assert_allclose(np.asarray(a)[..., :2], np.asarray(b)[..., :2], atol=atol)
    np.testing.assert_allclose(angle_diff(np.asarray(a)[..., 2], np.asarray(b)[..., 2]), 0.0, atol=atol)


def test_compose_with_inverse_is_identity(poses):
    a, _, _ = poses
    _assert_pose_close(compose(a, inverse(a)), np.zeros_like(a))
    _assert_pose_close(compose(inverse(a), a), np.zeros_like(a))
    _assert_pose_close(inverse(inverse(a)), a)


def test_compose_is_associative_and_matches_matrices(poses):
    a, b, c = poses
    _assert_pose_close(compose(compose(a, b), c), compose(a, compose(b, c)))
    _assert_pose_close(compose(a, b), matrix_to_se2(se2_to_matrix(a) @ se2_to_matrix(b)))
    _assert_pose_close(matrix_to_se2(se2_to_matrix(a)), a)


def test_relative_pose_recovers_second(poses):
    T_w_a, T_w_b, _ = poses
    T_a_b = relative_pose(T_w_a, T_w_b)
    _assert_pose_close(compose(T_w_a, T_a_b), T_w_b)


def test_known_composition():
    # Frame b sits 2 m ahead of a and is turned 90 degrees left; 1 m ahead of b is 2 m ahead + 1 m left of a.
    T_a_b = np.array([2.0, 0.0, np.pi / 2])
    np.testing.assert_allclose(transform_points(T_a_b, np.array([[1.0, 0.0]])), [[2.0, 1.0]], atol=1e-12)
    T_b_c = np.array([1.0, 0.0, np.pi / 2])
    _assert_pose_close(compose(T_a_b, T_b_c), [2.0, 1.0, np.pi])


def test_wrap_angle_range():
    a = np.linspace(-20, 20, 4001)
    w = wrap_angle(a)
    assert np.all(w > -np.pi) and np.all(w <= np.pi)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-12)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
    assert wrap_angle(-np.pi) == pytest.approx(np.pi)
    assert wrap_angle(3 * np.pi) == pytest.approx(np.pi)
    assert angle_diff(np.pi - 0.1, -np.pi + 0.1) == pytest.approx(0.2)


def test_transform_points_matches_compose(poses):
    a, b, _ = poses
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(20, 2)) * 30
    for i in range(5):
        via_two = transform_points(a[i], transform_points(b[i], pts))
        via_compose = transform_points(compose(a[i], b[i]), pts)
        np.testing.assert_allclose(via_two, via_compose, atol=1e-9)
        np.testing.assert_allclose(transform_points(inverse(a[i]), transform_points(a[i], pts)), pts, atol=1e-9)
    # distances are preserved
    moved = transform_points(a[0], pts)
    np.testing.assert_allclose(np.linalg.norm(moved[1:] - moved[0], axis=1),
                               np.linalg.norm(pts[1:] - pts[0], axis=1), atol=1e-9)
