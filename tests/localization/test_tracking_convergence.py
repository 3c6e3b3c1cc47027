"""Tracking's registration along a road: it converges to the true pose from anywhere within its first
association radius (one fit per radius recovered only part of an along-road offset), and a prior whose
uncertainty that radius does not cover is not one to track from (``TrackingConfig.covers``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from reradar_core.features import ScanFeatures
from reradar_core.geometry.se2 import compose, inverse, transform_points
from reradar_core.localization import PosePrior, TrackingConfig
from reradar_core.localization.tracking import register_from_prior
from reradar_core.matching import build_landmark_grid


def _road(rng: np.random.Generator) -> np.ndarray:
    """World landmarks of a straight road along +x: two kerb/facade lines 7 m either side (one return per metre,
    at random places along them), and 120 posts and corners scattered beside it."""
    walls = np.concatenate([np.column_stack([rng.uniform(-80, 200, 280), np.full(280, s * 7.0)])
                            for s in (-1.0, 1.0)])
    walls += rng.normal(scale=0.05, size=walls.shape)
    posts = np.column_stack([rng.uniform(-80, 200, 120), rng.choice([-1.0, 1.0], 120) * rng.uniform(9, 40, 120)])
    return np.concatenate([walls, posts])


def _scan(world: np.ndarray, T_world_sensor: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The landmarks within 60 m of the sensor, in its frame (x forward, y left), with 5 cm noise."""
    pts = transform_points(inverse(T_world_sensor), world)
    pts = pts[np.hypot(pts[:, 0], pts[:, 1]) < 60.0]
    return pts + rng.normal(scale=0.05, size=pts.shape)


def test_registration_converges_along_the_road_from_its_first_radius() -> None:
    rng = np.random.default_rng(3)
    world = _road(rng)
    T_world_kf = np.array([40.0, 0.5, 0.02])
    grid = build_landmark_grid(_scan(world, T_world_kf, rng))
    T_world_q = np.array([44.0, 0.0, 0.0])
    q = _scan(world, T_world_q, rng)
    query = ScanFeatures(np.ones(4), q, np.ones((len(q), 4)), 0)
    truth = compose(inverse(T_world_kf), T_world_q)
    cfg = TrackingConfig()
    for behind in (2.0, 3.0, 4.0):  # a prior this far behind the vehicle along the road, sigma 2 m (radius 4 m)
        T_world_prior = T_world_q - np.array([behind, 0.0, 0.0])
        start = compose(inverse(T_world_kf), T_world_prior)
        radii = cfg.radii(PosePrior(T_world_prior, 2.0, math.radians(2.0)))
        reg = register_from_prior(query, grid, start, radii)
        assert np.hypot(*(reg.T_keyframe_query[:2] - truth[:2])) < 0.15, behind
        assert abs(reg.T_keyframe_query[2] - truth[2]) < math.radians(0.5)
        assert reg.inlier_ratio > 0.9
        # one least-squares fit per radius (the registration before): left most of the way behind the vehicle
        one = register_from_prior(query, grid, start, radii, max_steps=1)
        assert np.hypot(*(one.T_keyframe_query[:2] - truth[:2])) > 0.5 * behind, behind
    # a prior 4 m behind with sigma 1 m (radius 2 m): the registration stays near the prior - why a prior must be
    # covered by the first radius (``TrackingConfig.covers``) and a last pose without odometry is no prior
    T_world_prior = T_world_q - np.array([4.0, 0.0, 0.0])
    reg = register_from_prior(query, grid, compose(inverse(T_world_kf), T_world_prior),
                              cfg.radii(PosePrior(T_world_prior, 1.0, math.radians(2.0))))
    assert np.hypot(*(reg.T_keyframe_query[:2] - truth[:2])) > 3.0


@pytest.mark.parametrize(("sigma", "covered"), [(0.5, True), (2.0, True), (3.0, True), (3.01, False), (6.0, False)])
def test_a_prior_is_tracked_from_only_while_the_first_radius_covers_it(sigma: float, covered: bool) -> None:
    cfg = TrackingConfig()  # first radius 2 sigma, capped at 6 m
    assert cfg.covers(PosePrior(np.zeros(3), sigma, 0.05)) is covered
    assert TrackingConfig(max_start_radius_m=12.0).covers(PosePrior(np.zeros(3), 6.0, 0.05))
