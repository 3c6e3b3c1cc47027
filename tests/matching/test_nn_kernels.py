"""The compiled nearest-landmark look-up (``matching.nn_kernels``, ``LandmarkGrid.nearest``) gives the KD-tree's
answers number for number, and ``estimate_pose_guided`` gives the same numbers with and without it."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from reradar_core.geometry.se2 import inverse, transform_points
from reradar_core.jit import jit_enabled
from reradar_core.matching import LandmarkGrid, build_landmark_grid, estimate_pose_guided
from reradar_core.matching.nn_kernels import bucket_landmarks, nearest_within

pytest.importorskip("numba")

RADII = (0.3, 0.4, 0.6, 0.75, 1.0, 2.0, 3.5, 10.0)


@pytest.fixture(autouse=True)
def _jit_on(monkeypatch):
    monkeypatch.setenv("RERADAR_JIT", "1")
    assert jit_enabled()


def _same_as_tree(grid: LandmarkGrid, xy: np.ndarray, bound: float) -> None:
    """``grid.nearest`` is ``grid.tree.query`` bit for bit (distances, indices, dtypes)."""
    want_d, want_i = grid.tree.query(xy, distance_upper_bound=bound)
    got_d, got_i = grid.nearest(xy, bound)
    assert got_d.dtype == want_d.dtype and got_i.dtype == want_i.dtype
    assert got_d.tobytes() == want_d.tobytes()
    np.testing.assert_array_equal(got_i, want_i)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("m", [1, 7, 300])
def test_kernel_is_the_tree_on_random_points(seed: int, m: int) -> None:
    """Random landmarks and points (many outside the bucket grid, some far away), every radius: the kernel's
    answers are the tree's and nothing is left to the tree (ties are measure-zero here)."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-60, 60, (m, 2))
    tree = cKDTree(pts)
    xy = np.vstack([rng.uniform(-80, 80, (3000, 2)), pts[:50] + rng.normal(0, 0.5, (min(m, 50), 2)),
                    [[1e6, 0.0], [-1e9, 1e9], [0.0, -3e15]]])
    for cell_m, max_cells in ((2.0, 8192), (0.5, 1 << 20), (2.0, 16)):  # the last one widens the cells
        buckets = bucket_landmarks(pts, cell_m, max_cells)
        assert buckets.nx * buckets.ny <= max(max_cells, 1) and buckets.cell_m >= cell_m
        for bound in RADII:
            dist, idx, unsure = nearest_within(xy, bound, buckets, m)
            want_d, want_i = tree.query(xy, distance_upper_bound=bound)
            assert not unsure.any()
            assert dist.tobytes() == want_d.tobytes()
            np.testing.assert_array_equal(idx, want_i)


@pytest.mark.parametrize("bound", [*RADII, np.inf])
def test_grid_nearest_is_the_tree_query(bound: float) -> None:
    rng = np.random.default_rng(5)
    grid = build_landmark_grid(rng.uniform(-50, 50, (400, 2)))
    _same_as_tree(grid, rng.uniform(-70, 70, (5000, 2)), bound)
    _same_as_tree(grid, np.zeros((0, 2)), bound)


def test_nothing_within_the_bound() -> None:
    rng = np.random.default_rng(6)
    pts = rng.uniform(-10, 10, (50, 2))
    grid = build_landmark_grid(pts)
    xy = rng.uniform(30, 40, (100, 2))
    dist, idx, unsure = nearest_within(xy, 2.0, grid.buckets(), len(pts))
    assert np.all(np.isinf(dist)) and np.all(idx == len(pts)) and not unsure.any()
    _same_as_tree(grid, xy, 2.0)
    _same_as_tree(grid, xy, np.inf)  # beyond the search cell: the tree answers


def test_exact_tie_and_point_at_the_bound_are_the_trees() -> None:
    """Equidistant landmarks (which one wins is the tree's traversal order) and a landmark exactly at the bound
    (scipy compares squared distances strictly below the squared bound) are flagged and left to the tree."""
    pts = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [5.0, 5.0], [5.0, 5.0]])  # a duplicate, too
    grid = build_landmark_grid(pts)
    xy = np.array([[0.0, 0.0], [5.0, 5.5], [1.75, 0.0], [1.0, 0.5], [3.0, 3.0]])
    for bound, flagged in ((2.0, [True, True, False, False, False]), (0.75, [False, True, True, False, False]),
                           (0.5, [False, True, False, True, False])):
        _, _, unsure = nearest_within(xy, bound, grid.buckets(), len(pts))
        np.testing.assert_array_equal(unsure, flagged)
        _same_as_tree(grid, xy, bound)
    _same_as_tree(grid, xy, np.inf)


def test_lattice_with_many_ties_and_exact_radii() -> None:
    """Landmarks and points on lattices: many exact ties and points exactly at the radii - still the tree's."""
    rng = np.random.default_rng(3)
    for _ in range(20):
        grid = build_landmark_grid(rng.integers(-20, 20, (150, 2)).astype(float) * 0.5)
        xy = rng.integers(-50, 50, (500, 2)).astype(float) * 0.25
        for bound in (0.25, 0.5, 0.75, 1.0, 2.0, np.inf):
            _same_as_tree(grid, xy, bound)


def test_non_finite_points_raise_as_the_tree_does() -> None:
    grid = build_landmark_grid(np.random.default_rng(0).uniform(-5, 5, (20, 2)))
    for bad in (np.nan, np.inf):
        with pytest.raises(ValueError):
            grid.tree.query(np.array([[bad, 0.0]]), distance_upper_bound=1.0)
        with pytest.raises(ValueError):
            grid.nearest(np.array([[0.0, 0.0], [bad, 0.0]]), 1.0)


def test_grid_from_within_mask_looks_up_the_same() -> None:
    rng = np.random.default_rng(9)
    pts = rng.uniform(-40, 40, (256, 2))
    full = build_landmark_grid(pts)
    packed = np.packbits(full.within_mask(1.5)[:-1])
    grid = LandmarkGrid.from_within_mask(packed, full.size, full.origin_m, full.cell_m, 1.5, pts)
    assert grid.buckets() is not None and grid.buckets().nbytes < 64 * 1024
    for bound in (0.75, 2.0, np.inf):
        _same_as_tree(grid, rng.uniform(-50, 50, (2000, 2)), bound)


def test_no_landmarks_falls_back_to_the_tree() -> None:
    grid = LandmarkGrid.from_within_mask(np.zeros(1, np.uint8), 2, -1.0, 0.5, 1.5, np.zeros((0, 2)))
    assert grid.buckets() is None
    _same_as_tree(grid, np.array([[0.0, 0.0]]), 1.0)


def _scene(T_dst_src: np.ndarray, seed: int, lattice: bool = False):
    """Walls and poles in the destination frame, 80 % of them seen from the source pose plus clutter; one
    random unit descriptor per 5 m cell (shared by the landmarks in it, like the model's)."""
    rng = np.random.default_rng(seed)
    walls = [np.column_stack([np.linspace(-50, 50, 120), np.full(120, y)]) for y in (-12.0, 14.0)]
    walls.append(np.column_stack([np.full(60, 30.0), np.linspace(-40, 40, 60)]))
    dst = np.vstack(walls + [rng.uniform(-55, 55, size=(80, 2))])
    if lattice:
        dst = np.unique(np.round(dst * 2) / 2, axis=0)
    keep = rng.random(len(dst)) < 0.8
    src = transform_points(inverse(T_dst_src), dst[keep])
    if not lattice:
        src = src + rng.normal(0, 0.1, size=src.shape)
    src = np.vstack([src, rng.uniform(-55, 55, size=(60, 2))])

    def desc(points: np.ndarray, salt: int) -> np.ndarray:
        cells = np.floor(points / 5.0).astype(np.int64)
        out = np.stack([np.random.default_rng(abs(int(a * 100003 + b)) + salt).normal(size=32) for a, b in cells])
        return (out / np.linalg.norm(out, axis=1, keepdims=True)).astype(np.float16)

    desc_src = np.vstack([desc(dst[keep], 7), desc(src[keep.sum():] + 1000.0, 7)])
    return src, desc_src, dst, desc(dst, 7)


def _estimate(monkeypatch, jit: str, *args, **kwargs):
    monkeypatch.setenv("RERADAR_JIT", jit)
    return estimate_pose_guided(*args, **kwargs)


@pytest.mark.parametrize("case", range(8))
def test_estimate_pose_guided_is_the_same_with_and_without_the_kernel(monkeypatch, case: int) -> None:
    rng = np.random.default_rng(100 + case)
    T = np.array([*rng.uniform(-8, 8, 2), rng.uniform(-np.pi, np.pi)])
    if case < 6:  # structured: walls and poles, plain or on a 0.5 m lattice (exact ties and radii)
        src, desc_src, dst, desc_dst = _scene(T, seed=case, lattice=case >= 4)
    else:  # random landmarks and descriptors: mostly failures, with their best poses and masks
        src, dst = rng.uniform(-50, 50, (300, 2)), rng.uniform(-50, 50, (350, 2))
        desc_src, desc_dst = rng.normal(size=(300, 16)), rng.normal(size=(350, 16))
    for grid in (None, build_landmark_grid(dst)):  # one built per call, and one shared by both paths
        a = _estimate(monkeypatch, "0", src, desc_src, dst, desc_dst, grid=grid)
        b = _estimate(monkeypatch, "1", src, desc_src, dst, desc_dst, grid=grid)
        assert a.pose.tobytes() == b.pose.tobytes()
        np.testing.assert_array_equal(a.inlier_mask, b.inlier_mask)
        assert (a.success, a.num_inliers, a.inlier_ratio, a.reason, a.num_iterations) == \
               (b.success, b.num_inliers, b.inlier_ratio, b.reason, b.num_iterations)
        assert np.float64(a.ambiguity).tobytes() == np.float64(b.ambiguity).tobytes()
        assert np.float64(a.rmse_m).tobytes() == np.float64(b.rmse_m).tobytes()
    if case < 4:
        assert b.success and np.linalg.norm(b.pose[:2] - T[:2]) < 0.5
