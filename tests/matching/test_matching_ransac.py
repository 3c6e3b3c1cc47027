"""RANSAC 2-D rigid estimation: known transforms at any heading under outliers and noise, failure modes."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.errors import ConfigError
from reradar_core.geometry.se2 import angle_diff, transform_points
from reradar_core.matching import RansacConfig, estimate_rigid_2d, fit_rigid_2d


def _problem(yaw_deg: float, seed: int, n: int = 300, outlier_frac: float = 0.6, noise_m: float = 0.3):
    rng = np.random.default_rng(seed)
    T_dst_src = np.array([rng.uniform(-30, 30), rng.uniform(-30, 30), np.radians(yaw_deg)])
    src = rng.uniform(-60, 60, (n, 2))
    dst = transform_points(T_dst_src, src) + rng.normal(0, noise_m, (n, 2))
    outlier = np.zeros(n, dtype=bool)
    outlier[rng.permutation(n)[: int(round(outlier_frac * n))]] = True
    dst[outlier] = rng.uniform(-90, 90, (outlier.sum(), 2))
    return src, dst, T_dst_src, outlier


@pytest.mark.parametrize("yaw_deg", [0.0, 37.0, 90.0, 179.5, 180.0, 181.0, 225.0, 270.0, 359.0])
def test_recovers_known_transform_any_heading(yaw_deg):
    src, dst, T, outlier = _problem(yaw_deg, seed=int(yaw_deg * 10))
    est = estimate_rigid_2d(src, dst)
    assert est.success and est.reason is None
    assert np.linalg.norm(est.pose[:2] - T[:2]) <= 0.3
    assert np.degrees(angle_diff(est.pose[2], T[2])) <= 0.5
    assert -np.pi < est.pose[2] <= np.pi
    # inliers are (nearly) the true correspondences: 1 m threshold vs 0.3 m noise keeps ~99 %
    assert est.num_inliers >= 0.9 * (~outlier).sum()
    assert np.sum(est.inlier_mask & outlier) <= 3
    assert est.inlier_ratio == pytest.approx(est.num_inliers / len(src))
    assert est.inlier_mask.shape == (len(src),) and est.inlier_mask.dtype == bool


def test_exact_data_exact_answer():
    rng = np.random.default_rng(11)
    src = rng.uniform(-50, 50, (40, 2))
    T = np.array([3.0, -4.0, np.radians(200.0)])
    est = estimate_rigid_2d(src, transform_points(T, src))
    np.testing.assert_allclose(est.pose[:2], T[:2], atol=1e-9)
    assert angle_diff(est.pose[2], T[2]) < 1e-9
    assert est.num_inliers == 40 and est.rmse_m < 1e-9


def test_direction_is_T_dst_src():
    src = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0], [3.0, 1.0], [-2.0, 4.0], [5.0, -1.0]])
    dst = src + [10.0, 0.0]  # destination points are the source points shifted 10 m along x
    est = estimate_rigid_2d(src, dst)
    np.testing.assert_allclose(est.pose, [10.0, 0.0, 0.0], atol=1e-9)


def test_deterministic_with_seed():
    src, dst, _, _ = _problem(123.0, seed=5, outlier_frac=0.7)
    a = estimate_rigid_2d(src, dst, RansacConfig(seed=3))
    b = estimate_rigid_2d(src, dst, RansacConfig(seed=3))
    np.testing.assert_array_equal(a.pose, b.pose)
    np.testing.assert_array_equal(a.inlier_mask, b.inlier_mask)
    assert a.num_iterations == b.num_iterations


def test_adaptive_iterations_stop_early_on_clean_data():
    src, dst, _, _ = _problem(45.0, seed=6, outlier_frac=0.0)
    est = estimate_rigid_2d(src, dst)
    assert est.num_iterations <= 64  # one chunk suffices for 100 % inliers
    src2, dst2, _, _ = _problem(45.0, seed=6, outlier_frac=0.95)
    assert estimate_rigid_2d(src2, dst2, RansacConfig(max_iterations=200)).num_iterations <= 200


def test_too_few_matches():
    est = estimate_rigid_2d(np.zeros((2, 2)), np.ones((2, 2)))
    assert not est.success and "too few matches" in est.reason
    assert np.all(np.isnan(est.pose)) and est.num_inliers == 0
    est0 = estimate_rigid_2d(np.zeros((0, 2)), np.zeros((0, 2)))
    assert not est0.success and est0.inlier_ratio == 0.0 and est0.inlier_mask.shape == (0,)


def test_too_few_inliers_reports_best_pose():
    rng = np.random.default_rng(8)
    src = rng.uniform(-50, 50, (30, 2))
    dst = rng.uniform(-50, 50, (30, 2))  # no consistent transform: at most a couple of chance inliers
    est = estimate_rigid_2d(src, dst)
    assert not est.success and "too few inliers" in est.reason
    assert est.num_inliers < 6


def test_degenerate_inputs():
    coincident = np.ones((10, 2))
    est = estimate_rigid_2d(coincident, coincident + 1.0)
    assert not est.success and "degenerate" in est.reason
    bad = np.ones((10, 2))
    bad[3, 1] = np.nan
    est_nan = estimate_rigid_2d(bad, np.ones((10, 2)))
    assert not est_nan.success and "non-finite" in est_nan.reason
    est_inf = estimate_rigid_2d(np.ones((10, 2)), np.full((10, 2), np.inf))
    assert not est_inf.success and "non-finite" in est_inf.reason


def test_colinear_points_are_fine():
    src = np.column_stack([np.linspace(-20, 20, 12), np.zeros(12)])
    T = np.array([1.0, 2.0, np.radians(300.0)])
    est = estimate_rigid_2d(src, transform_points(T, src))
    assert est.success
    np.testing.assert_allclose(est.pose[:2], T[:2], atol=1e-9)


def test_shape_errors_raise():
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        estimate_rigid_2d(np.zeros((5, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError):
        estimate_rigid_2d(np.zeros((5, 2)), np.zeros((4, 2)))


def test_config_validation_and_defaults():
    cfg = RansacConfig()
    assert (cfg.inlier_threshold_m, cfg.max_iterations, cfg.confidence, cfg.min_matches, cfg.min_inliers,
            cfg.seed) == (1.0, 1000, 0.999, 3, 6, 0)
    for bad in (dict(inlier_threshold_m=0), dict(max_iterations=0), dict(confidence=1.0), dict(min_matches=1),
                dict(min_inliers=1)):
        with pytest.raises(ConfigError):
            RansacConfig(**bad)


def test_fit_rigid_2d_least_squares():
    rng = np.random.default_rng(9)
    src = rng.uniform(-10, 10, (50, 2))
    T = np.array([-2.0, 7.0, 2.8])
    noise = rng.normal(0, 0.05, (50, 2))
    pose = fit_rigid_2d(src, transform_points(T, src) + noise)
    np.testing.assert_allclose(pose[:2], T[:2], atol=0.05)
    assert angle_diff(pose[2], T[2]) < np.radians(0.5)
