"""Tiny synthetic scans for the baseline tests (made here, no files)."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.benchmark.synthetic import render_scan, synthetic_world


@pytest.fixture(scope="session")
def world() -> np.ndarray:
    return synthetic_world(seed=3)


@pytest.fixture(scope="session")
def scans(world):
    """Five scans at distinct places (80 m apart) plus the first place seen again 1.5 m away."""
    poses = np.array([[0.0, 0.0, 0.3], [80.0, 0.0, 1.0], [0.0, 80.0, -0.5], [-80.0, 0.0, 2.0],
                      [0.0, -80.0, 0.0], [1.5, 0.5, 0.3]])
    return [render_scan(world, p, "boreas", noise_seed=i) for i, p in enumerate(poses)], poses
