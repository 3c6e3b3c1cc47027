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


@pytest.mark.parametrize("cell_m", [0.5, 0.3])
def test_best_screen_counts_are_the_largest_counts(cell_m: float) -> None:
    """The pruned per-candidate maximum over bit-packed masks equals the maximum of the full counts."""
    from reradar_core.localization.screening import build_screen_grid
    from reradar_core.matching.kernels import best_aligned_screen, count_aligned_screen

    rng = np.random.default_rng(5)
    cfg = AlignmentConfig(grid_cell_m=cell_m)
    grids = [build_screen_grid(rng.uniform(-40, 40, (m, 2)), cfg) for m in (300, 40, 500, 2)]
    src = rng.uniform(-50, 50, (128, 2))
    v = 900
    cand = np.sort(rng.integers(0, 3, v))  # candidate 3 has no hypothesis: its best is 0
    yaw = rng.uniform(-np.pi, np.pi, v)
    c, s = np.cos(yaw), np.sin(yaw)
    tx, ty = rng.uniform(-5, 5, v), rng.uniform(-5, 5, v)
    c[:40], s[:40], tx[:40], ty[:40] = 1.0, 0.0, 0.0, 0.0  # identity poses: high counts early, so pruning bites
    sizes = np.array([g.n for g in grids], np.int64)
    origins = np.array([g.origin_m for g in grids])
    inverse = cell_m == 0.5
    cells = np.array([1.0 / g.cell_m if inverse else g.cell_m for g in grids])
    near = np.concatenate([g.near for g in grids] + [np.zeros(1, np.uint8)])
    offsets = np.concatenate([[0], np.cumsum(sizes * sizes)[:-1]])
    full = count_aligned_screen(src[:, 0].copy(), src[:, 1].copy(), c, s, tx, ty, cand, origins, cells, inverse,
                                sizes, offsets, near)
    expected = np.zeros(len(grids), np.int64)
    np.maximum.at(expected, cand, full)
    bit_offsets = np.concatenate([[0], np.cumsum([len(g.packed) for g in grids])[:-1]]).astype(np.int64) * 8
    packed = np.concatenate([g.packed for g in grids])
    got = best_aligned_screen(src[:, 0].copy(), src[:, 1].copy(), c, s, tx, ty, cand, origins, cells, inverse,
                              sizes, bit_offsets, packed, len(grids))
    np.testing.assert_array_equal(got, expected)
    assert expected[3] == 0 and expected[:3].min() > 0


def test_pair_verdicts_agree_with_the_numpy_test() -> None:
    """Outside its margin the squared-length verdict is the numpy ``abs(ls - hypot) < m``; at exact ties it
    hands the minimal set back (borderline) instead of guessing."""
    from reradar_core.matching.kernels import PAIR_BORDERLINE, PAIR_CONSISTENT, consistent_pairs_screen

    rng = np.random.default_rng(6)
    fx = np.concatenate([rng.uniform(-60, 60, 400), [0.0, 3.0, 0.0]])
    fy = np.concatenate([rng.uniform(-60, 60, 400), [0.0, 4.0, 0.0]])
    land = rng.integers(0, 400, (3, 200))
    land[:, :2] = [400, 401]  # keyframe pair 5 m apart
    h = 700
    a, b = rng.integers(0, 200, h), rng.integers(0, 200, h)
    a[:3], b[:3] = 0, 1
    ls = rng.uniform(0, 80, h)
    ls[:3] = [2.0, 8.0, 5.0]  # |ls - 5| = 3 exactly twice: the numpy test says no (not < 3); 0 < 3: yes
    verdict = np.empty((3, h), np.int8)
    consistent_pairs_screen(land, a, b, fx, fy, ls, ls > 1.0, 3.0, verdict)
    i, j = land[:, a], land[:, b]
    numpy_ok = (ls > 1.0)[None, :] & (np.abs(ls[None, :] - np.hypot(fx[j] - fx[i], fy[j] - fy[i])) < 3.0)
    sure = verdict != PAIR_BORDERLINE
    np.testing.assert_array_equal((verdict == PAIR_CONSISTENT)[sure], numpy_ok[sure])
    assert (verdict[:, :2] == PAIR_BORDERLINE).all() and (verdict[:, 2] == PAIR_CONSISTENT).all()
    assert sure.mean() > 0.99


def test_screen_scores_equal_the_numpy_path_on_a_lattice(monkeypatch: pytest.MonkeyPatch) -> None:
    """Landmarks on a 1 m lattice: many minimal sets whose lengths differ by exactly the allowed mismatch."""
    rng = np.random.default_rng(7)
    cfg = AlignmentConfig()
    def rows(n: int) -> np.ndarray:  # integer x on three rows: lengths within a row are whole metres
        return np.column_stack([rng.integers(-40, 40, n), rng.choice([0.0, 10.0, 20.0], n)]).astype(np.float64)

    kfs = [screen_keyframe(rows(300) + shift, _unit(rng.normal(size=(300, 16))), cfg) for shift in (0.0, 1.0, 3.0)]
    q_desc = _unit(rng.normal(size=(260, 16)))
    q_pts = rows(260)
    spied: list[int] = []
    import reradar_core.localization.screening as screening
    from reradar_core.matching.kernels import PAIR_BORDERLINE

    def spy(*args):  # type: ignore[no-untyped-def]
        screening_kernel(*args)
        spied.append(int((args[-1] == PAIR_BORDERLINE).sum()))

    screening_kernel = screening.consistent_pairs_screen
    monkeypatch.setattr(screening, "consistent_pairs_screen", spy)
    a, b = _both(monkeypatch, screen_candidates, q_pts, q_desc, kfs, cfg)
    np.testing.assert_array_equal(a, b)
    assert a.max() > 0 and spied and spied[0] > 0  # the borderline minimal sets were met (and decided alike)
