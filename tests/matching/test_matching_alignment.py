"""Descriptor-guided, alignment-scored pose estimation: known transforms with coarse (shared) descriptors."""

import math

import numpy as np
import pytest

from reradar_core.geometry.se2 import angle_diff, inverse, transform_points
from reradar_core.matching import AlignmentConfig, build_landmark_grid, count_aligned, estimate_pose_guided

CELL_M = 5.0  # descriptors shared by every landmark in a 5 m cell, like the model's F' cells


def _coarse_descriptors(points_world: np.ndarray, rng_seed: int = 7, dim: int = 32) -> np.ndarray:
    cells = np.floor(points_world / CELL_M).astype(np.int64)
    keys = cells[:, 0] * 100003 + cells[:, 1]
    out = np.empty((len(points_world), dim))
    for i, k in enumerate(keys):  # one random unit vector per cell, stable across scans
        out[i] = np.random.default_rng(abs(int(k)) + rng_seed).normal(size=dim)
    return (out / np.linalg.norm(out, axis=1, keepdims=True)).astype(np.float16)


def _scene(T_dst_src: np.ndarray, seed: int = 0):
    rng = np.random.default_rng(seed)
    # walls (dense lines) and scattered poles in the destination (keyframe) frame
    walls = [np.column_stack([np.linspace(-50, 50, 120), np.full(120, y)]) for y in (-12.0, 14.0)]
    walls.append(np.column_stack([np.full(60, 30.0), np.linspace(-40, 40, 60)]))
    poles = rng.uniform(-55, 55, size=(80, 2))
    dst = np.vstack(walls + [poles])
    keep = rng.random(len(dst)) < 0.8  # the query sees 80 % of the keyframe's landmarks
    src_true = transform_points(inverse(T_dst_src), dst[keep]) + rng.normal(0, 0.1, size=(keep.sum(), 2))
    clutter = rng.uniform(-55, 55, size=(60, 2))
    src = np.vstack([src_true, clutter])
    desc_dst = _coarse_descriptors(dst)
    desc_src = np.vstack([_coarse_descriptors(dst[keep]), _coarse_descriptors(clutter + 1000.0)])
    return src, desc_src, dst, desc_dst


@pytest.mark.parametrize("yaw_deg", [0.0, 37.0, 135.0, 200.0, 290.0, 359.0])
def test_known_transform_recovered_at_any_heading(yaw_deg):
    T = np.array([3.5, -2.0, np.radians(yaw_deg)])
    src, dsrc, dst, ddst = _scene(T)
    est = estimate_pose_guided(src, dsrc, dst, ddst)
    assert est.success, est.reason
    assert np.linalg.norm(est.pose[:2] - T[:2]) < 0.3
    assert np.degrees(angle_diff(est.pose[2], T[2])) < 0.5
    assert est.num_inliers >= 0.7 * (len(src) - 60)


def test_deterministic_for_a_seed_and_grid_reuse_gives_same_answer():
    T = np.array([1.0, 2.0, 0.4])
    src, dsrc, dst, ddst = _scene(T, seed=3)
    a = estimate_pose_guided(src, dsrc, dst, ddst, AlignmentConfig(seed=5))
    b = estimate_pose_guided(src, dsrc, dst, ddst, AlignmentConfig(seed=5), grid=build_landmark_grid(dst))
    np.testing.assert_allclose(a.pose, b.pose)
    assert a.num_inliers == b.num_inliers


def test_unrelated_landmarks_align_few():
    rng = np.random.default_rng(1)
    src = rng.uniform(-50, 50, size=(200, 2))
    dst = rng.uniform(-50, 50, size=(200, 2))
    d = rng.normal(size=(200, 16)).astype(np.float16)
    est = estimate_pose_guided(src, d, dst, d[::-1].copy(), AlignmentConfig(min_inliers=60))
    assert not est.success and est.reason == "too_few_inliers"
    assert est.inlier_ratio < 0.3


@pytest.mark.parametrize("n", [0, 1])
def test_too_few_landmarks_is_a_result_not_an_exception(n):
    pts = np.zeros((n, 2))
    est = estimate_pose_guided(pts, np.zeros((n, 8)), np.ones((5, 2)), np.ones((5, 8)))
    assert not est.success and est.reason == "too_few_landmarks"


def test_non_finite_input_is_rejected_with_a_reason():
    pts = np.array([[0.0, 0.0], [np.nan, 1.0], [2.0, 2.0]])
    est = estimate_pose_guided(pts, np.ones((3, 4)), pts[[0, 2, 0]] + 1, np.ones((3, 4)))
    assert not est.success and est.reason == "non_finite_input"


def test_screen_scores_the_true_place_above_a_different_place():
    from reradar_core.matching import screen_alignment

    T = np.array([2.0, 4.0, np.radians(75.0)])
    src, dsrc, dst, ddst = _scene(T, seed=1)
    rng = np.random.default_rng(3)  # another place: walls at other offsets, other poles
    walls = [np.column_stack([np.linspace(-50, 50, 120), np.full(120, y)]) for y in (-4.0, 27.0)]
    walls.append(np.column_stack([np.full(60, -21.0), np.linspace(-40, 40, 60)]))
    other = np.vstack(walls + [rng.uniform(-55, 55, size=(80, 2))])
    dother = _coarse_descriptors(other, rng_seed=11)
    right = screen_alignment(src, dsrc, dst, ddst)
    wrong = screen_alignment(src, dsrc, other, dother)
    cached = screen_alignment(src, dsrc, dst, ddst, grid=build_landmark_grid(dst))
    assert right == cached  # a cached grid gives the same score
    assert right > 0.6 and wrong < right - 0.2
    assert screen_alignment(src[:1], dsrc[:1], dst, ddst) == 0.0  # degenerate input scores 0, never raises


def test_unique_scene_has_low_ambiguity():
    T = np.array([3.5, -2.0, np.radians(37.0)])
    src, dsrc, dst, ddst = _scene(T)
    est = estimate_pose_guided(src, dsrc, dst, ddst)
    assert est.success and est.ambiguity < 0.8


def test_periodic_scene_is_refused_as_ambiguous():
    # a lattice of identical posts, 8 m apart, seen with identical descriptors: shifting the answer by one
    # period aligns exactly as many landmarks, so no single pose can be right
    g = np.arange(-48.0, 49.0, 8.0)
    dst = np.array([(x, y) for x in g for y in g])
    T = np.array([1.0, 0.5, 0.0])
    src = transform_points(inverse(T), dst)
    desc = np.ones((len(dst), 8), np.float32) / np.sqrt(8)
    est = estimate_pose_guided(src, desc, dst, desc, AlignmentConfig(top_k_matches=8))
    assert not est.success and est.reason == "ambiguous" and est.ambiguity >= 1.0
    relaxed = estimate_pose_guided(src, desc, dst, desc, AlignmentConfig(top_k_matches=8, max_ambiguity=np.inf))
    assert relaxed.success  # the same answer is accepted only when ambiguity checking is switched off


def test_count_aligned_counts_the_landmarks_a_pose_brings_within_the_radius():
    """Known answers: every landmark under the true pose, none under a pose 5 m off in a sparse scene, and the
    true pose turned by 20 degrees loses the far landmarks (a landmark 50 m out moves 17 m)."""
    rng = np.random.default_rng(0)
    dst = rng.uniform(-60, 60, (40, 2))
    dst = dst[np.min(np.hypot(*(dst[:, None] - dst[None]).transpose(2, 0, 1)) + np.eye(40) * 1e3, axis=1) > 6.0]
    T = np.array([3.0, -2.0, math.radians(30.0)])
    src = transform_points(inverse(T), dst)
    grid = build_landmark_grid(dst)
    counts = count_aligned(np.array([T, T + [5.0, 0.0, 0.0], T + [0.0, 0.0, math.radians(20.0)]]), src, grid, 1.5)
    assert counts.dtype == np.int64 and counts[0] == len(dst) and counts[1] == 0 and counts[2] < len(dst) // 4


def test_count_within_equals_the_distance_lookup():
    rng = np.random.default_rng(5)
    grid = build_landmark_grid(rng.uniform(-40, 40, (120, 2)), 0.5)
    # points inside, on the edges of and far outside the grid, and non-finite ones
    x = rng.uniform(-70, 70, (50, 128))
    y = rng.uniform(-70, 70, (50, 128))
    x[0, :4] = [np.nan, np.inf, -np.inf, 1e12]
    for thr in (0.75, 1.5, 3.0):
        with np.errstate(invalid="ignore"):  # non-finite points: a cast warning, and never within
            expected = (grid.lookup(x, y) < thr).sum(axis=1)
            np.testing.assert_array_equal(grid.count_within(x, y, thr), expected)


@pytest.mark.parametrize("n", [512, 320, 319, 100, 1000])
def test_topk_last_axis_is_torch_topks_order(n: int) -> None:
    """The same indices in the same order as ``torch.topk(sorted=False)`` (the seeded draws index that
    order), also for rows with ties, repeated values, NaN and -inf padding, and in any leading shape."""
    import torch

    from reradar_core.matching.alignment import topk_last_axis

    rng = np.random.default_rng(n)
    sim = rng.normal(size=(40, 7, n)).astype(np.float32)
    sim[0, 0, :] = 0.5                                   # all equal
    sim[1, 0, 10:20] = sim[1, 0].max() + 1               # ten tied maxima
    sim[2, 0, [3, 9]] = 7.0                              # tie inside the top k
    sim[3, 0, -3:] = -np.inf                             # padding
    sim[4, 0, :] = np.round(sim[4, 0] * 2) / 2           # many repeated values
    sim[5, 0, 17] = np.nan
    sim[6, 0, :] = -np.inf
    sim[6, 0, :6] = [1, 2, 3, 4, 5, 6]                   # exactly k + 1 finite values
    sim[7, 0, :] = -np.inf
    sim[7, 0, :5] = [3, 1, 3, 2, 0]                      # k finite values with a tie, then padding
    want = torch.topk(torch.from_numpy(sim.copy()), 5, dim=2, sorted=False).indices.numpy()
    got = topk_last_axis(sim.copy(), 5)
    assert got.shape == want.shape
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(topk_last_axis(sim[0].copy(), 5), want[0])


def test_batched_refinement_is_the_per_hypothesis_refinement_bit_for_bit() -> None:
    """``_refine_all`` (one KD-tree query per iteration for all hypotheses) returns exactly what refining each
    hypothesis on its own returns: same pose bits, same masks - for good, poor and hopeless starts, and for
    hypotheses that stop early (fewer than 3 landmarks associated)."""
    from reradar_core.matching.alignment import _refine_all, refine_pose

    T = np.array([3.5, -2.0, np.radians(37.0)])
    src, _, dst, _ = _scene(T, seed=4)
    grid = build_landmark_grid(dst)
    rng = np.random.default_rng(2)
    starts = [T + rng.normal(0, s, 3) * [1, 1, 0.05] for s in (0.0, 0.3, 1.0, 3.0, 10.0)]
    starts += [np.array([500.0, 500.0, 0.0]), np.array([0.0, 0.0, np.pi])]  # nothing (or little) associates
    for thresholds in ((2.0, 1.0, 0.75, 0.75), (3.0,), (0.5, 2.0)):
        got = _refine_all(src, grid, starts, thresholds)
        want = [refine_pose(src, grid, p, thresholds) for p in starts]
        assert len(got) == len(want)
        for (pose, mask), (pose_ref, mask_ref) in zip(got, want, strict=True):
            assert pose.tobytes() == pose_ref.tobytes()
            np.testing.assert_array_equal(mask, mask_ref)
    assert _refine_all(src, grid, [], (2.0,)) == []
    pose, mask = _refine_all(src, grid, starts, (2.0, 1.0))[0]
    assert mask.sum() >= 0.7 * (len(src) - 60) and np.linalg.norm(pose[:2] - T[:2]) < 0.3


@pytest.mark.parametrize("jit", ["0", "1"])  # the numpy path (skipped look-ups) and the compiled refinement
def test_batched_refinement_skips_no_look_up_it_needs_on_exact_radii(monkeypatch, jit) -> None:  # type: ignore[no-untyped-def]
    """Landmarks on a lattice, so many query landmarks lie exactly at the association radii (the skipped
    look-ups are those that cannot find a landmark within the shrinking radius; the compiled look-ups flag
    those ties for the KD-tree): still the per-hypothesis answer of the KD-tree path, bit for bit."""
    from reradar_core.matching.alignment import _refine_all, refine_pose

    rng = np.random.default_rng(3)
    for trial in range(40):
        dst = rng.integers(-20, 20, (150, 2)).astype(float) * 0.5
        src = rng.integers(-20, 20, (120, 2)).astype(float) * 0.25
        grid = build_landmark_grid(dst)
        starts = [np.zeros(3)] + [np.array([*rng.normal(0, 0.5, 2), rng.normal(0, 0.05)]) for _ in range(4)]
        thresholds = ((2.0, 1.0, 0.75, 0.75), (1.5, 1.0, 0.5, 0.25), (1.0, 0.5))[trial % 3]
        monkeypatch.setenv("RERADAR_JIT", jit)
        got = _refine_all(src, grid, starts, thresholds)
        monkeypatch.setenv("RERADAR_JIT", "0")
        for (pose, mask), start in zip(got, starts, strict=True):
            pose_ref, mask_ref = refine_pose(src, grid, start, thresholds)
            assert pose.tobytes() == pose_ref.tobytes()
            np.testing.assert_array_equal(mask, mask_ref)


@pytest.mark.parametrize("cell_m", [0.5, 0.3])
@pytest.mark.parametrize("rows", [128, 300])
def test_count_within_columns_equals_the_distance_lookup(cell_m: float, rows: int) -> None:
    """The scorer's column layout (one pose per column; the division by a power-of-two cell done as a
    multiplication; a uint8 sum below 256 rows) counts exactly what the distance look-up counts."""
    rng = np.random.default_rng(6)
    grid = build_landmark_grid(rng.uniform(-40, 40, (120, 2)), cell_m)
    x = rng.uniform(-70, 70, (rows, 50))
    y = rng.uniform(-70, 70, (rows, 50))
    x[:4, 0] = [np.nan, np.inf, -np.inf, 1e12]
    x[:, 1] = np.round(x[:, 1] / cell_m) * cell_m  # exactly on cell edges
    for thr in (0.75, 1.5, 3.0):
        with np.errstate(invalid="ignore"):  # non-finite points: a cast warning, and never within
            expected = (grid.lookup(x, y) < thr).sum(axis=0)
            np.testing.assert_array_equal(grid._count_within_columns(x, y, thr), expected)
            np.testing.assert_array_equal(grid.count_within(x.T, y.T, thr), expected)


def test_apply_all_is_the_stacked_apply_bit_for_bit() -> None:
    from reradar_core.matching.alignment import _apply, _apply_all

    rng = np.random.default_rng(8)
    for n in (1, 2, 7, 128, 513):
        pts = rng.uniform(-80, 80, (n, 2))
        poses = [np.array([*rng.normal(0, 20, 2), rng.uniform(-7, 7)]) for _ in range(5)]
        want = np.stack([_apply(p, pts) for p in poses])
        assert _apply_all(poses, pts).tobytes() == want.tobytes()
        assert _apply_all(poses[:1], pts).tobytes() == want[:1].tobytes()


def _fit_rigid_2d_reference(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """``fit_rigid_2d`` as first written (one numpy call per term): the weighted fit's arithmetic."""
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    mu_s, mu_d = w @ src, w @ dst
    a, b = src - mu_s, dst - mu_d
    yaw = math.atan2(np.sum(w * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])),
                     np.sum(w * (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])))
    c, s = math.cos(yaw), math.sin(yaw)
    t = mu_d - np.array([c * mu_s[0] - s * mu_s[1], s * mu_s[0] + c * mu_s[1]])
    return np.array([t[0], t[1], yaw])


def _fit_rigid_2d_loops(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The unweighted fit written as plain left-to-right loops: what ``fit_rigid_2d`` and the compiled
    refinement (``nn_kernels.refine_poses``) both compute."""
    n = len(src)
    ms0, ms1, md0, md1 = src[0, 0], src[0, 1], dst[0, 0], dst[0, 1]
    for i in range(1, n):
        ms0, ms1, md0, md1 = ms0 + src[i, 0], ms1 + src[i, 1], md0 + dst[i, 0], md1 + dst[i, 1]
    ms0, ms1, md0, md1 = ms0 / n, ms1 / n, md0 / n, md1 / n
    cross = dot = 0.0
    for i in range(n):
        a0, a1, b0, b1 = src[i, 0] - ms0, src[i, 1] - ms1, dst[i, 0] - md0, dst[i, 1] - md1
        cr, dt = a0 * b1 - a1 * b0, a0 * b0 + a1 * b1
        cross, dot = (cr, dt) if i == 0 else (cross + cr, dot + dt)
    yaw = math.atan2(cross, dot)
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([md0 - (c * ms0 - s * ms1), md1 - (s * ms0 + c * ms1), yaw])


def test_fit_rigid_2d_keeps_the_reference_arithmetic_bit_for_bit() -> None:
    from reradar_core.matching import fit_rigid_2d

    rng = np.random.default_rng(10)
    for n in (2, 3, 8, 9, 127, 128, 129, 300, 1000):
        src = rng.uniform(-90, 90, (n, 2))
        yaw = rng.uniform(-4, 4)
        rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
        dst = src @ rot.T + rng.normal(0, 30, 2) + rng.normal(0, 0.3, (n, 2))
        keep = rng.random(n) < 0.6
        keep[:2] = True
        for s, d in ((src, dst), (src[keep], dst[keep])):  # contiguous, and rows picked by a mask
            got = fit_rigid_2d(s, d)
            assert got.tobytes() == _fit_rigid_2d_loops(s, d).tobytes()
            np.testing.assert_allclose(got, _fit_rigid_2d_reference(s, d), rtol=0, atol=1e-9)  # same fit
            w = rng.uniform(0.1, 3.0, len(s))
            assert fit_rigid_2d(s, d, w).tobytes() == _fit_rigid_2d_reference(s, d, w).tobytes()


def test_hypotheses_are_those_of_solving_every_draw_then_filtering() -> None:
    """The reference: solve all drawn minimal sets with row arithmetic, keep the length-consistent ones."""
    from reradar_core.matching.alignment import _hypotheses

    rng = np.random.default_rng(12)
    src, dst = rng.uniform(-60, 60, (300, 2)), rng.uniform(-60, 60, (280, 2))
    pairs = np.stack([np.repeat(np.arange(300), 5), rng.integers(0, 280, 1500)], axis=1)
    cfg = AlignmentConfig(num_hypotheses=3000, max_length_mismatch_m=10.0)
    draw = np.random.default_rng(4)
    a, b = draw.integers(0, len(pairs), 3000), draw.integers(0, len(pairs), 3000)
    s1, s2, d1, d2 = src[pairs[a, 0]], src[pairs[b, 0]], dst[pairs[a, 1]], dst[pairs[b, 1]]
    vs, vd = s2 - s1, d2 - d1
    ls, ld = np.hypot(vs[:, 0], vs[:, 1]), np.hypot(vd[:, 0], vd[:, 1])
    ok = (ls > cfg.min_pair_separation_m) & (np.abs(ls - ld) < cfg.max_length_mismatch_m)
    yaw = np.arctan2(vd[:, 1], vd[:, 0]) - np.arctan2(vs[:, 1], vs[:, 0])
    c, s = np.cos(yaw), np.sin(yaw)
    ms, md = (s1 + s2) / 2, (d1 + d2) / 2
    want = np.stack([md[:, 0] - (c * ms[:, 0] - s * ms[:, 1]), md[:, 1] - (s * ms[:, 0] + c * ms[:, 1]), yaw],
                    axis=1)[ok]
    got = _hypotheses(src, dst, pairs, cfg, np.random.default_rng(4))
    assert 0 < len(got) < 3000 and got.tobytes() == want.tobytes()


def test_topk_last_axis_of_rows_that_are_not_contiguous() -> None:
    """A strided view (rows not next to each other) gives the same indices as its contiguous copy."""
    from reradar_core.matching.alignment import topk_last_axis

    rng = np.random.default_rng(13)
    wide = rng.normal(size=(60, 520)).astype(np.float32)
    wide[3, 10:20] = 9.0  # ties: the torch path for that row
    view = wide[:, 4:516]
    want = topk_last_axis(np.ascontiguousarray(view), 5)
    np.testing.assert_array_equal(topk_last_axis(view, 5), want)
    np.testing.assert_array_equal(topk_last_axis(np.asfortranarray(view), 5), want)


def test_polish_fits_the_pose_to_the_closest_pairs_and_keeps_the_count() -> None:
    """A third of the landmarks doubled by a ghost 0.7 m aside (a second return of the same object): the
    refinement's 0.75 m association takes both and is pulled ~0.17 m towards the ghosts; the polish at
    0.6 / 0.5 / 0.4 m keeps the true pairs only.
    The inlier count (counted at 0.75 m, what the floor and the confidence use) does not change."""
    T = np.array([3.0, -2.0, math.radians(25.0)])
    rng = np.random.default_rng(4)
    dst = rng.uniform(-50, 50, size=(300, 2))
    src = transform_points(inverse(T), dst) + rng.normal(0, 0.03, size=dst.shape)
    ghosts = transform_points(inverse(T), dst[:100] + np.array([0.0, 0.7]))
    src_all = np.vstack([src, ghosts])
    desc_dst = _coarse_descriptors(dst)
    desc_src = np.vstack([desc_dst, desc_dst[:100]])
    plain = estimate_pose_guided(src_all, desc_src, dst, desc_dst, AlignmentConfig(polish_thresholds_m=()))
    polished = estimate_pose_guided(src_all, desc_src, dst, desc_dst, AlignmentConfig())
    assert plain.success and polished.success
    err = {name: math.hypot(*(e.pose[:2] - T[:2])) for name, e in (("plain", plain), ("polished", polished))}
    assert err["plain"] > 0.1  # pulled towards the ghosts
    assert err["polished"] < 0.02
    assert polished.num_inliers == plain.num_inliers
    np.testing.assert_array_equal(polished.inlier_mask, plain.inlier_mask)
    with pytest.raises(Exception, match="polish_thresholds_m"):
        AlignmentConfig(polish_thresholds_m=(0.5, 0.0))


def _corridor(T_dst_src: np.ndarray, descriptor_shift_m: float):
    """A corridor: two rows of posts along x (a landmark every 3 m, so they align at every 3 m shift along the
    road) and 40 poles (which align at the true pose only). The query's descriptors are those of the place
    ``descriptor_shift_m`` further along x: every descriptor pair then points 0.5-10.5 m away from the truth,
    like the few true pairs left between real scans 15 m apart.
    (A corridor is also symmetric under a half turn; the poles break that.)"""
    rng = np.random.default_rng(21)
    x = np.arange(-60.0, 60.0, 3.0)
    walls = np.vstack([np.column_stack([x, np.full(len(x), y)]) for y in (-8.0, 8.0)])
    poles = np.column_stack([rng.uniform(-50, 50, 40), rng.choice([-1, 1], 40) * rng.uniform(10, 30, 40)])
    dst = np.vstack([walls, poles])
    src = transform_points(inverse(T_dst_src), dst) + rng.normal(0, 0.05, size=dst.shape)
    desc_dst = _coarse_descriptors(dst)
    desc_src = _coarse_descriptors(dst + np.array([descriptor_shift_m, 0.0]))
    return src, desc_src, dst, desc_dst


def test_local_search_finds_the_true_pose_along_a_corridor_when_no_hypothesis_is_near_it() -> None:
    """Known answer: without the local search every hypothesis lies metres along the corridor and the walls
    align there (the poles do not); the local search around that answer reaches the true pose, where the
    poles align too (more landmarks), and takes it."""
    T = np.array([2.0, 0.5, math.radians(30.0)])
    src, dsrc, dst, ddst = _corridor(T, descriptor_shift_m=5.5)
    plain = estimate_pose_guided(src, dsrc, dst, ddst, AlignmentConfig(local_search_m=0.0))
    searched = estimate_pose_guided(src, dsrc, dst, ddst, AlignmentConfig())
    assert math.hypot(*(plain.pose[:2] - T[:2])) > 2.0  # the hypotheses alone: a wrong place on the corridor
    assert searched.success
    assert math.hypot(*(searched.pose[:2] - T[:2])) < 0.1
    assert np.degrees(angle_diff(searched.pose[2], T[2])) < 0.2
    assert searched.num_inliers > plain.num_inliers
    assert searched.num_inliers >= 0.95 * len(src)


def test_local_search_leaves_a_right_answer_alone_and_rejects_bad_settings() -> None:
    T = np.array([3.5, -2.0, np.radians(137.0)])
    src, dsrc, dst, ddst = _scene(T)
    plain = estimate_pose_guided(src, dsrc, dst, ddst, AlignmentConfig(local_search_m=0.0))
    searched = estimate_pose_guided(src, dsrc, dst, ddst, AlignmentConfig())
    np.testing.assert_array_equal(searched.pose, plain.pose)
    assert searched.num_inliers == plain.num_inliers
    for bad in ({"local_search_m": -1.0}, {"local_search_step_m": 0.0}, {"local_search_starts": 0}):
        with pytest.raises(Exception, match="local_search"):
            AlignmentConfig(**bad)
