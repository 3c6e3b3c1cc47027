"""QA session 38: geometry helpers given the wrong shape or units failed as IndexErrors or answered wrongly."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.errors import ConfigError
from reradar_core.evaluation.metrics import pose_error
from reradar_core.geometry.cartesian import CartesianConfig
from reradar_core.geometry.se2 import check_yaw_radians, compose, inverse, transform_points


def test_pose_helpers_name_a_wrong_shape() -> None:
    xy = np.zeros((5, 2))
    for call in (lambda: compose(xy, xy), lambda: inverse(xy), lambda: pose_error(xy, xy)):
        with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
            call()
    with pytest.raises(ValueError, match=r"single \(3,\) pose"):
        transform_points(np.zeros((4, 3)), xy)
    with pytest.raises(ValueError, match=r"points_b must be \(N, 2\)"):
        transform_points(np.zeros(3), np.zeros((4, 3)))
    np.testing.assert_allclose(transform_points(np.array([1.0, 2.0, np.pi / 2]), np.array([[1.0, 0.0]])),
                               [[1.0, 3.0]], atol=1e-12)


def test_a_straight_drive_with_headings_in_degrees_is_refused() -> None:
    north_deg = np.c_[np.zeros(40), np.arange(40) * 3.0, np.full(40, 90.0)]
    with pytest.raises(ConfigError, match="look like degrees"):
        check_yaw_radians(north_deg)
    check_yaw_radians(np.c_[np.zeros(40), np.arange(40) * 3.0, np.full(40, np.pi / 2)])  # radians: fine
    a = np.linspace(0.0, 4 * np.pi, 200)  # two laps of a circle, unwrapped radians: fine
    check_yaw_radians(np.c_[50 * np.cos(a), 50 * np.sin(a), a + np.pi / 2])


def test_cartesian_config_needs_whole_pixels_and_a_finite_resolution() -> None:
    with pytest.raises(ConfigError, match="whole number of pixels"):
        CartesianConfig(200.5, 0.64)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="positive and finite"):
        CartesianConfig(201, float("inf"))
    assert CartesianConfig(np.int64(201), 0.64).width_px == 201
