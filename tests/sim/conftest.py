"""Shared fixtures for the simulator tests: straight roads, static / moving trajectories, known targets."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.io.poses import PoseSequence
from reradar_core.sim.sensor import SensorConfig
from reradar_core.sim.world import RoadNetwork

T0 = 1_600_000_000_000_000


def straight_road(length_m: float = 1200.0) -> RoadNetwork:
    x = np.linspace(-length_m / 2, length_m / 2, 200)
    return RoadNetwork([np.column_stack([x, np.zeros_like(x)])])


def linear_trajectory(x0: float = 0.0, y0: float = 0.0, yaw: float = 0.0, speed_mps: float = 0.0) -> PoseSequence:
    """Poses at T0 - 1 s .. T0 + 1 s, moving along ``yaw`` at ``speed_mps`` and at (x0, y0) at T0."""
    t = T0 + np.array([-1_000_000, 0, 1_000_000], dtype=np.int64)
    s = (t - T0) / 1e6 * speed_mps
    xy = np.column_stack([x0 + s * np.cos(yaw), y0 + s * np.sin(yaw)])
    return PoseSequence(t, xy, np.full(3, yaw))


#: Sensor model without the random interference streaks / multipath ghosts, for known-target checks.
CLEAN = SensorConfig(streak_rate=0.0, ghost_prob=0.0)


@pytest.fixture(scope="session")
def road() -> RoadNetwork:
    return straight_road()
