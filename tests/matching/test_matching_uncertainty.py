"""Pose covariance of a registration (``matching.uncertainty``): the least-squares figure on known geometry, what a
wall leaves free, the fitted scales, frames, and the ``Localizer``'s answers carrying it in the map frame."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.se2 import inverse, transform_points
from reradar_core.localization import InMemoryKeyframes, LocalizationConfig, Localizer, PosePrior
from reradar_core.matching.motion import (
    MotionConfig,
    azimuth_time_offsets,
    deskew_points,
    deskewed,
    motion_polish,
)
from reradar_core.matching.ransac import fit_rigid_2d
from reradar_core.matching.uncertainty import (
    PoseCovarianceConfig,
    landmark_information,
    registration_covariance,
    rotate_covariance,
)
from reradar_core.retrieval import GlobalIndex

UNSCALED = PoseCovarianceConfig(position_scale=1.0, heading_scale=1.0, prior_sigma_m=1e3, prior_sigma_deg=180.0)


def _poles(n: int = 60, radius: float = 20.0) -> np.ndarray:
    """``n`` poles on a circle, 2.1 m apart at the defaults: each alone within the 1.5 m neighbourhood (W = I)."""
    a = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return np.column_stack([radius * np.cos(a), radius * np.sin(a)])


def test_isolated_poles_give_the_least_squares_covariance() -> None:
    # N poles at radius rho around the sensor, each seen with isotropic noise sigma: H = diag(N, N, N rho^2), so the
    # pose's standard deviations are sigma / sqrt(N) and sigma / (rho sqrt(N))
    rng = np.random.default_rng(0)
    poles, sigma = _poles(), 0.05
    query = poles + rng.normal(scale=sigma, size=poles.shape)
    cov = registration_covariance(query, poles, np.zeros(3), UNSCALED)
    assert cov is not None
    n, rho = len(poles), 20.0
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), [sigma / math.sqrt(n), sigma / math.sqrt(n),
                                                       sigma / (rho * math.sqrt(n))], rtol=0.25)
    # and it is the spread of the least-squares pose over many such scans (Monte Carlo)
    fits = np.array([fit_rigid_2d(poles + rng.normal(scale=sigma, size=poles.shape), poles) for _ in range(400)])
    np.testing.assert_allclose(fits.std(axis=0), np.sqrt(np.diag(cov)), rtol=0.25)


def test_a_wall_leaves_the_pose_loose_along_it() -> None:
    rng = np.random.default_rng(1)
    wall = np.column_stack([np.arange(-40.0, 40.0, 0.3), np.full(267, 6.0)])  # a façade along x, 6 m to the left
    poles = np.array([[12.0, -9.0], [-18.0, -8.0], [30.0, -11.0]])
    scene = np.vstack([wall, poles])
    cov = registration_covariance(scene + rng.normal(scale=0.05, size=scene.shape), scene, np.zeros(3), UNSCALED)
    assert cov is not None
    sx, sy = math.sqrt(cov[0, 0]), math.sqrt(cov[1, 1])
    assert sx > 5.0 * sy  # along the wall only the three poles pin it; across it every point of the wall does
    # the wall's points pin only their normal; a pole pins both directions
    w = landmark_information(scene, np.array([100, len(wall)]), cKDTree(scene))
    np.testing.assert_allclose(w[0], [[0.0, 0.0], [0.0, 1.0]], atol=1e-6)
    np.testing.assert_allclose(w[1], np.eye(2))
    # a wall alone: the pose is free along it, reported as loose as the prior (10 m), not as precise
    alone = registration_covariance(wall + rng.normal(scale=0.05, size=wall.shape), wall, np.zeros(3))
    assert alone is not None
    assert math.sqrt(alone[0, 0]) == pytest.approx(10.0, rel=0.01) and math.sqrt(alone[1, 1]) < 0.1


def test_the_fitted_scales_multiply_the_variances() -> None:
    rng = np.random.default_rng(2)
    poles = _poles()
    query = poles + rng.normal(scale=0.05, size=poles.shape)
    base = registration_covariance(query, poles, np.zeros(3), UNSCALED)
    scaled = registration_covariance(query, poles, np.zeros(3), PoseCovarianceConfig(
        position_scale=4.0, heading_scale=9.0, prior_sigma_m=1e3, prior_sigma_deg=180.0))
    assert base is not None and scaled is not None
    np.testing.assert_allclose(np.sqrt(np.diag(scaled) / np.diag(base)), [2.0, 2.0, 3.0], rtol=1e-6)
    # a rigid registration's pose (no motion compensation) takes the rigid scales
    rigid = registration_covariance(query, poles, np.zeros(3), PoseCovarianceConfig(
        rigid_position_scale=25.0, rigid_heading_scale=4.0, prior_sigma_m=1e3, prior_sigma_deg=180.0),
        motion_compensated=False)
    assert rigid is not None
    np.testing.assert_allclose(np.sqrt(np.diag(rigid) / np.diag(base)), [5.0, 5.0, 2.0], rtol=1e-6)


def test_covariance_turns_with_the_frame() -> None:
    cov = np.diag([4.0, 0.01, 1e-4])  # loose along the keyframe's x
    turned = rotate_covariance(cov, math.pi / 2)  # a keyframe heading north: loose along the map's y
    np.testing.assert_allclose(turned, np.diag([0.01, 4.0, 1e-4]), atol=1e-12)
    # a full covariance turned by 30 deg, by hand: position block R C R^T, position-heading column R c, heading alone
    full = np.array([[0.04, 0.01, 0.002], [0.01, 0.09, -0.003], [0.002, -0.003, 1e-4]])
    c, s = math.cos(math.radians(30.0)), math.sin(math.radians(30.0))
    r = np.array([[c, -s], [s, c]])
    want = np.empty((3, 3))
    want[:2, :2] = r @ full[:2, :2] @ r.T
    want[:2, 2] = want[2, :2] = r @ full[:2, 2]
    want[2, 2] = full[2, 2]
    np.testing.assert_allclose(rotate_covariance(full, math.radians(30.0)), want, atol=1e-15)
    # a point 1 m along the keyframe's x with its error, turned with the frame: the same mahalanobis distance
    err_kf = np.array([0.1, -0.2, 0.004])
    err_map = np.concatenate([r @ err_kf[:2], err_kf[2:]])
    assert err_map @ np.linalg.solve(want, err_map) == pytest.approx(err_kf @ np.linalg.solve(full, err_kf))


def test_too_few_pairs_or_bad_input_give_none() -> None:
    poles = _poles()
    assert registration_covariance(poles[:5], poles, np.zeros(3)) is None
    assert registration_covariance(poles + 5.0, poles, np.zeros(3)) is None  # nothing within 0.75 m
    bad = poles.copy()
    bad[0, 0] = np.nan
    assert registration_covariance(bad, poles, np.zeros(3)) is None
    assert registration_covariance(poles, poles, np.array([0.0, np.inf, 0.0])) is None


@pytest.mark.parametrize("bad", [{"radius_m": 0.0}, {"radius_m": 50.0}, {"position_scale": float("nan")},
                                 {"heading_scale": 0.0}, {"min_pairs": 2}, {"neighbours": 100},
                                 {"prior_sigma_m": -1.0}, {"prior_sigma_m": 1e6}, {"prior_sigma_deg": 1e6}])
def test_covariance_settings_out_of_range_fail_at_construction(bad: dict) -> None:
    with pytest.raises(ConfigError):
        PoseCovarianceConfig(**bad)


def test_localizer_answers_carry_their_covariance_in_the_map_frame() -> None:
    rng = np.random.default_rng(4)
    # a street along the map's y axis (keyframes heading north): a façade on one side, poles on the other
    wall = np.column_stack([np.full(500, -7.0), np.linspace(-80.0, 80.0, 500)])
    poles = np.column_stack([rng.uniform(6.0, 30.0, 40), rng.uniform(-80.0, 80.0, 40)])
    world = np.vstack([wall, poles])
    desc = rng.normal(size=(len(world), 16))
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    n = 4
    poses = np.column_stack([np.zeros(n), np.arange(n) * 8.0, np.full(n, math.pi / 2)])
    stamps = (np.arange(n) * 1_000_000).astype(np.int64)
    g = rng.normal(size=(n, 16)).astype(np.float32)
    g /= np.linalg.norm(g, axis=1, keepdims=True)

    def features(T_w_s: np.ndarray, gd: np.ndarray, ts: int) -> ScanFeatures:
        local = transform_points(inverse(T_w_s), world)
        keep = np.hypot(local[:, 0], local[:, 1]) < 60.0
        return ScanFeatures(gd, local[keep] + rng.normal(scale=0.03, size=(int(keep.sum()), 2)), desc[keep], ts)

    kfs = [features(poses[i], g[i], int(stamps[i])) for i in range(n)]
    loc = Localizer(GlobalIndex(g), InMemoryKeyframes(kfs, poses, stamps))
    query = features(poses[2] + np.array([0.4, 1.0, 0.01]), g[2], 10**9)
    rigid = LocalizationConfig(motion=MotionConfig(enabled=False))  # unskewed scans: compare with the rigid pose's
    res = loc.localize(query, rigid)
    assert res.localized and res.pose_covariance is not None and not res.motion_compensated
    cov = res.pose_covariance
    assert cov.shape == (3, 3) and np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
    assert cov[1, 1] > 4.0 * cov[0, 0]  # loose along the street (the map's y), pinned across it by the façade
    # the same covariance as the registration's, turned from the keyframe's frame (heading north) into the map's
    kid = res.best.keyframe_id
    in_keyframe = registration_covariance(query.keypoints_xy_m, kfs[kid].keypoints_xy_m, res.best.T_keyframe_query,
                                          motion_compensated=False)
    assert in_keyframe is not None
    np.testing.assert_allclose(cov, rotate_covariance(in_keyframe, math.pi / 2), rtol=1e-9, atol=1e-15)
    assert "covariance_ms" in res.timings_ms
    off = loc.localize(query, LocalizationConfig(motion=MotionConfig(enabled=False),
                                                 covariance=PoseCovarianceConfig(enabled=False)))
    assert off.localized and off.pose_covariance is None
    np.testing.assert_allclose(off.T_map_query, res.T_map_query)
    # a scan seen from a sensor moving at 8 m/s (as the map drive): the motion compensation (the default) answers the
    # compensated pose, and its covariance is that of the de-skewed landmarks, with the compensated pose's scales
    twist = np.array([8.0, 0.0, 0.0])
    T_w_q = poses[2] + np.array([0.4, 1.0, 0.01])
    local = transform_points(inverse(T_w_q), world)
    keep = np.hypot(local[:, 0], local[:, 1]) < 60.0
    tau = azimuth_time_offsets(local[keep])
    seen = deskew_points(local[keep], tau, -twist)  # first order: where the moving sensor sees them
    moving = ScanFeatures(g[2], seen, desc[keep], 10**9)
    compensated = loc.localize(moving)
    assert compensated.localized and compensated.motion_compensated and compensated.pose_covariance is not None
    kid = compensated.best.keyframe_id
    twists, _ = loc.keyframe_twists()
    np.testing.assert_allclose(twists[kid], twist, atol=1e-6)
    src_fit = deskewed(seen, _fitted_twist(loc, moving, kid), MotionConfig())
    want = registration_covariance(src_fit, deskewed(kfs[kid].keypoints_xy_m, twists[kid], MotionConfig()),
                                   compensated.best.T_keyframe_query, motion_compensated=True)
    assert want is not None
    # (the twist refitted here agrees with the Localizer's to ~1e-6: a tolerance well inside what de-skewing changes)
    np.testing.assert_allclose(compensated.pose_covariance, rotate_covariance(want, math.pi / 2), rtol=1e-4)
    as_seen = registration_covariance(seen, kfs[kid].keypoints_xy_m, compensated.best.T_keyframe_query)
    assert as_seen is not None
    assert not np.allclose(compensated.pose_covariance, rotate_covariance(as_seen, math.pi / 2), rtol=1e-2)
    # the covariance changes no pose: the same compensated answer with it off
    no_cov = loc.localize(moving, LocalizationConfig(covariance=PoseCovarianceConfig(enabled=False)))
    assert no_cov.pose_covariance is None and no_cov.motion_compensated
    np.testing.assert_array_equal(no_cov.T_map_query, compensated.T_map_query)
    # a tracked answer carries one too, in the same map frame
    tracked = loc.track(moving, PosePrior(compensated.T_map_query, 0.5, math.radians(1.0)))
    assert tracked.mode == "tracking" and tracked.localized and tracked.pose_covariance is not None
    np.testing.assert_allclose(np.sqrt(np.diag(tracked.pose_covariance)), np.sqrt(np.diag(compensated.pose_covariance)),
                               rtol=0.5)


def _fitted_twist(loc: Localizer, features: ScanFeatures, kid: int) -> np.ndarray:
    """The query motion the ``Localizer``'s compensation fits (``motion_polish`` from its rigid answer)."""
    rigid = loc.localize(features, LocalizationConfig(motion=MotionConfig(enabled=False)))
    twists, _ = loc.keyframe_twists()
    polished = motion_polish(features.keypoints_xy_m, loc.cache.get(kid).features.keypoints_xy_m,
                             rigid.best.T_keyframe_query, twists[kid])
    assert polished is not None
    return polished.twist
