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


# ---- QA session 37: poses a caller gets wrong -------------------------------------------------------------------
def test_check_poses_refuses_positions_only_non_finite_and_far_poses() -> None:
    import pytest

    from reradar_core.errors import ConfigError
    from reradar_core.geometry.se2 import check_poses

    good = np.array([[0.0, 1.0, 0.5], [2.0, 3.0, -0.5]])
    np.testing.assert_array_equal(check_poses(good), good)
    assert check_poses(good.astype(np.float32)).dtype == np.float64
    np.testing.assert_array_equal(check_poses(good[0]), good[:1])  # one pose
    with pytest.raises(ConfigError, match=r"\(N, 3\).*got shape \(18, 2\)"):
        check_poses(np.zeros((18, 2)))  # a reshape(-1, 3) made 12 interleaved poses of it
    bad = good.copy()
    bad[1, 2] = np.nan
    with pytest.raises(ConfigError, match="1 pose.*NaN or infinite.*row 1"):
        check_poses(bad, "keyframe poses")
    with pytest.raises(ConfigError, match="within"):
        check_poses(np.array([[2e7, 0.0, 0.0]]))


def _loop(turns: float, n: int = 200, radius: float = 50.0, offset_rad: float = 0.0) -> np.ndarray:
    """A vehicle driving ``turns`` times round a circle, heading along the road (unwrapped radians)."""
    a = np.linspace(0.0, 2 * np.pi * turns, n)
    return np.column_stack([radius * np.cos(a), radius * np.sin(a), a + np.pi / 2 + offset_rad])


def test_headings_in_degrees_are_refused_and_unwrapped_radians_are_not() -> None:
    import pytest

    from reradar_core.errors import ConfigError
    from reradar_core.geometry.se2 import check_yaw_radians, wrap_angle

    loop = _loop(3.0)  # unwrapped radians up to ~20.4 rad, beyond 2 pi
    check_yaw_radians(loop)
    check_yaw_radians(_loop(3.0, offset_rad=np.pi))  # a sensor mounted backwards
    wrapped = loop.copy()
    wrapped[:, 2] = wrap_angle(loop[:, 2])
    check_yaw_radians(wrapped)  # within pi: nothing to tell, passes
    degrees = wrapped.copy()
    degrees[:, 2] = np.degrees(wrapped[:, 2])
    with pytest.raises(ConfigError, match="look like degrees.*numpy.radians"):
        check_yaw_radians(degrees, "keyframe poses")
    # unwrapped radians on a straight road east, after a loop: 2 pi + 0.05 follows the road as radians (session 38:
    # the example used to be 7.0, which lies 41 degrees off the road as radians and 7 as degrees, i.e. degrees)
    straight = np.column_stack([np.arange(20.0), np.zeros(20), np.full(20, 2 * np.pi + 0.05)])
    check_yaw_radians(straight)
    with pytest.raises(ConfigError, match="look like degrees"):
        check_yaw_radians(np.column_stack([np.arange(20.0), np.zeros(20), np.full(20, 7.0)]))
    parked = np.column_stack([np.zeros(20), np.zeros(20), np.linspace(0, 90, 20)])  # no travel: cannot tell
    check_yaw_radians(parked)
