"""The compiled alignment counts (``matching.kernels``, ``reradar_core.jit``) give the numpy path's numbers."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.jit import jit_enabled
from reradar_core.localization.screening import screen_candidates, screen_keyframe
from reradar_core.matching import AlignmentConfig, build_landmark_grid, estimate_pose_guided
from reradar_core.matching.alignment import _score

pytestmark = pytest.mark.skipif(not jit_enabled(), reason="numba not installed (the numpy path is what runs)")


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _both(monkeypatch: pytest.MonkeyPatch, fn, *args):  # type: ignore[no-untyped-def]
    """``fn(*args)`` on the numpy path and on the compiled path."""
    monkeypatch.setenv("RERADAR_JIT", "0")
    with np.errstate(invalid="ignore"):  # the int64 cast of a NaN / huge cell (it falls outside either way)
        numpy_path = fn(*args)
    monkeypatch.setenv("RERADAR_JIT", "1")
    return numpy_path, fn(*args)


@pytest.mark.parametrize("cell_m", [0.5, 0.3])  # a power of two (multiplied by its inverse) and not
def test_pose_counts_equal_the_numpy_path(monkeypatch: pytest.MonkeyPatch, cell_m: float) -> None:
    rng = np.random.default_rng(1)
    grid = build_landmark_grid(rng.uniform(-40, 40, (300, 2)), cell_m)
    src = rng.uniform(-60, 60, (128, 2))  # partly off the grid under most poses
    poses = np.column_stack([rng.uniform(-20, 20, 700), rng.uniform(-20, 20, 700), rng.uniform(-4, 4, 700)])
    poses[:5] = [[0, 0, 0], [1e300, 0, 0], [-1e300, 0, 1], [0, 0, np.pi], [np.nan, 0, 0]]  # far off and NaN
    a, b = _both(monkeypatch, _score, poses, src, grid, 1.5)
    np.testing.assert_array_equal(a, b)
    assert a.dtype == b.dtype == np.int64 and a[1] == a[2] == a[4] == 0 and a.max() > 0


def test_screen_scores_equal_the_numpy_path(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(2)
    cfg = AlignmentConfig()
    base = rng.uniform(-60, 60, (260, 2))
    kfs = [screen_keyframe(p, _unit(rng.normal(size=(len(p), 16))), cfg)
           for p in (base, rng.uniform(-30, 30, (90, 2)), base[:120] + 1.0, rng.uniform(-80, 80, (400, 2)))]
    q_pts = np.vstack([base[:200] + rng.normal(0, 0.2, (200, 2)), rng.uniform(-60, 60, (40, 2))])
    q_desc = _unit(rng.normal(size=(240, 16)))
    a, b = _both(monkeypatch, screen_candidates, q_pts, q_desc, kfs, cfg)
    np.testing.assert_array_equal(a, b)
    assert a.max() > 0


def test_pose_estimate_equals_the_numpy_path(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(4)
    dst = rng.uniform(-60, 60, (400, 2))
    desc = _unit(rng.normal(size=(400, 16)))
    yaw = 0.4
    R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    src = (dst[:300] - [3.0, -2.0]) @ R + rng.normal(0, 0.1, (300, 2))  # dst = R src + t, with noise
    src_desc = _unit(desc[:300] + 0.05 * rng.normal(size=(300, 16)))
    a, b = _both(monkeypatch, estimate_pose_guided, src, src_desc, dst, desc)
    assert a.success and b.success
    np.testing.assert_array_equal(a.pose, b.pose)
    np.testing.assert_array_equal(a.inlier_mask, b.inlier_mask)
    assert a.num_inliers == b.num_inliers and a.ambiguity == b.ambiguity


def test_warm_up_compiles_only_when_the_kernels_run(monkeypatch: pytest.MonkeyPatch) -> None:
    from reradar_core.matching.kernels import warm_up

    assert warm_up() is True
    monkeypatch.setenv("RERADAR_JIT", "0")
    assert warm_up() is False
