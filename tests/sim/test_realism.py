"""Realism checks: scan statistics in the documented ranges, revisits, landmark repeatability + RANSAC."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from reradar_core.geometry.cartesian import CartesianConfig, polar_to_cartesian
from reradar_core.geometry.se2 import relative_pose
from reradar_core.landmarks import detect_landmarks
from reradar_core.matching import RansacConfig, estimate_rigid_2d
from reradar_core.sim.sensor import render_scan, scan_seed
from reradar_core.sim.stats import scan_statistics
from reradar_core.sim.traversal import Traversal
from reradar_core.sim.world import World

from .conftest import T0, linear_trajectory


@pytest.fixture(scope="module")
def urban(road):
    return World(road, seed=1, profile="urban")


def test_urban_scan_statistics_in_documented_ranges(urban):
    """docs/SIMULATOR.md: clear urban scans (Oxford preset) vs the real Oxford figures (mean 0.045,
    p99 0.29, 1,500-1,700 Cen 2018 keypoints)."""
    trav = Traversal(urban, seed=3)
    for k, x0 in enumerate((0.0, 120.0)):
        st = scan_statistics(render_scan(trav, linear_trajectory(x0=x0, speed_mps=8.0), T0, "oxford", scan_seed(3, k)))
        assert 0.025 <= st.mean <= 0.07, st
        assert 0.15 <= st.p99 <= 0.45, st
        assert 0.15 <= st.frac_zero <= 0.6, st
        assert 500 <= st.keypoints <= 4000, st


def _cart(scan):
    return polar_to_cartesian(scan, CartesianConfig(201, 0.64)).ravel()


def test_revisit_shares_static_structure_but_not_dynamics_or_noise(urban):
    traj = linear_trajectory(x0=40.0)
    a = render_scan(Traversal(urban, seed=1), traj, T0, "boreas", scan_seed(1, 0))
    b = render_scan(Traversal(urban, seed=2, condition="clear"), traj, T0, "boreas", scan_seed(2, 0))
    elsewhere = render_scan(Traversal(urban, seed=1), linear_trajectory(x0=340.0), T0, "boreas", scan_seed(1, 1))
    same_place = np.corrcoef(_cart(a), _cart(b))[0, 1]
    other_place = np.corrcoef(_cart(a), _cart(elsewhere))[0, 1]
    assert same_place > other_place + 0.2, (same_place, other_place)
    assert same_place < 0.95  # dynamic objects, parked cars and speckle differ
    assert np.mean(a.power != b.power) > 0.3


def test_rigid_transform_5m_apart_recovered_with_landmarks_and_ransac(urban):
    """Two scans 5 m apart: Cen 2018 landmarks repeat; with ground-truth correspondences (nearest landmark
    after the true transform) RANSAC recovers the transform."""
    trav = Traversal(urban, seed=4)
    p_a = np.array([60.0, 0.5, 0.0])
    p_b = np.array([65.0, 1.0, 0.12])
    sa = render_scan(trav, linear_trajectory(*p_a), T0, "boreas", scan_seed(4, 0))
    sb = render_scan(trav, linear_trajectory(*p_b), T0 + 250_000, "boreas", scan_seed(4, 1))
    la, lb = detect_landmarks(sa), detect_landmarks(sb)
    T_a_b = relative_pose(p_a, p_b)
    c, s = np.cos(T_a_b[2]), np.sin(T_a_b[2])
    b_in_a = lb.xy_m @ np.array([[c, s], [-s, c]]) + T_a_b[:2]
    d, j = cKDTree(la.xy_m).query(b_in_a, distance_upper_bound=0.5)
    ok = np.isfinite(d)
    assert ok.sum() >= 50, ok.sum()
    est = estimate_rigid_2d(lb.xy_m[ok], la.xy_m[j[ok]], RansacConfig(inlier_threshold_m=0.5, seed=0))
    assert est.success
    assert np.hypot(*(est.pose[:2] - T_a_b[:2])) < 0.15
    assert abs(np.degrees(est.pose[2] - T_a_b[2])) < 0.3
