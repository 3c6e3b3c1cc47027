"""QA session 38: a transposed point set fitted a wrong pose without a word."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.geometry.se2 import transform_points
from reradar_core.matching.ransac import fit_rigid_2d


def test_fit_rigid_2d_checks_its_points() -> None:
    src = np.random.default_rng(0).uniform(-20, 20, (10, 2))
    pose = np.array([3.0, -2.0, 0.4])
    dst = transform_points(pose, src)
    np.testing.assert_allclose(fit_rigid_2d(src, dst), pose, atol=1e-9)
    with pytest.raises(ValueError, match=r"both be \(N, 2\)"):
        fit_rigid_2d(src.T, dst.T)
    with pytest.raises(ValueError, match="N >= 2"):
        fit_rigid_2d(src[:1], dst[:1])
    with pytest.raises(ValueError, match="weights"):
        fit_rigid_2d(src, dst, weights=np.ones(3))
