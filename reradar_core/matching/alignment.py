"""Descriptor-guided RANSAC scored by whole-landmark alignment, then nearest-landmark refinement.

Why not plain mutual-nearest-neighbour RANSAC (paper, Sec. "Pose Estimation")? F' has one cell per
``stride`` input pixels (8 x 0.64 m = 5.1 m with the default model), so landmarks a few metres apart share
almost the same local descriptor: a keypoint's true partner is among its few most similar keypoints, rarely
the single mutual best, and counting inliers over such matches rewards wrong hypotheses along dense walls.
Measured on the simulator's smoke suite with the shipped weights (query vs ground-truth-nearest keyframe):
mutual NN + RANSAC at 1 m: 0 % of pairs within 2 m / 2 deg; at 3 m: 5 %; this estimator: 80-85 %, median
0.15-0.2 m / 0.4-0.5 deg (docs/BENCHMARKS.md).

The estimator:
1. pairs every source keypoint with its ``top_k_matches`` most similar destination keypoints (cosine);
2. draws ``num_hypotheses`` 2-point minimal sets from those pairs (seeded), keeps those whose two
   distances agree (a rigid motion preserves length) and solves each for (x, y, yaw) - any heading;
3. scores every hypothesis by how many source landmarks land within ``score_threshold_m`` of *any*
   destination landmark (a precomputed distance-transform grid makes this a table look-up);
4. refines the ``refine_candidates`` best hypotheses by iterated nearest-landmark association with
   shrinking thresholds and a least-squares fit, and keeps the one with most associated landmarks;
4b. searches around that answer: every translation within ``local_search_m`` on a ``local_search_step_m`` grid
   at the answer's heading is scored as in step 3, the best few distinct ones are refined as in step 4, and one
   that associates more landmarks replaces the answer (the hypotheses of step 2 need true descriptor pairs,
   which thin out as the scans move apart; the grid does not);
5. polishes that pose by a few more association + least-squares steps at radii below the counting radius
   (``polish_thresholds_m``): the inliers are still counted at the last refinement radius (0.75 m, what the
   floor and the confidence were fitted on), but the pose is fitted to the closest pairs only, which sharpens
   the heading (mean heading error on the training splits' unseen sessions: loop 0.531 -> 0.499 deg, Boreas
   0.287 -> 0.251, off-road 0.241 -> 0.228; correct answers the same, wrong 3 -> 2; docs/BENCHMARKS.md
   "Session 6").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from reradar_core.errors import ConfigError
from reradar_core.geometry.se2 import wrap_angle
from reradar_core.jit import jit_enabled
from reradar_core.matching.kernels import count_aligned_pose
from reradar_core.matching.nn_kernels import LandmarkBuckets, bucket_landmarks, nearest_within, refine_poses
from reradar_core.matching.ransac import RigidEstimate, fit_rigid_2d

__all__ = ["AlignmentConfig", "LandmarkGrid", "build_landmark_grid", "estimate_pose_guided", "refine_pose",
           "screen_alignment", "topk_last_axis"]


@dataclass(frozen=True)
class AlignmentConfig:
    """Settings of ``estimate_pose_guided`` (metres, counts).

    Attributes:
        top_k_matches: destination keypoints paired with each source keypoint (most similar first).
            5 covers the landmarks that share a 5 m F' cell.
        num_hypotheses: 2-point minimal sets drawn (before the length-consistency filter).
        min_pair_separation_m: minimal sets whose source points are closer than this fix the heading badly.
        max_length_mismatch_m: reject a minimal set whose two point distances differ by more (rigid motion
            preserves length; about half an F' cell of slack).
        score_threshold_m: a landmark counts as aligned within this distance when scoring hypotheses.
        score_points: source landmarks used for scoring (evenly subsampled; speed).
        refine_thresholds_m: association radii of the refinement iterations (coarse to fine).
        refine_candidates: best-scoring hypotheses that are refined.
        screen_hypotheses: minimal sets drawn by ``screen_alignment`` (the cheap candidate screen).
        screen_source_points: source landmarks (evenly subsampled) paired by descriptor in the screen.
        min_inliers: landmarks associated at the final radius for the pose to count.
        grid_cell_m: cell of the destination distance grid.
        ambiguity_separation_m, ambiguity_separation_rad: a hypothesis farther than this (translation, or
            heading) from the answer is a *rival* pose.
        max_ambiguity: the answer is refused (``reason="ambiguous"``) when the best rival aligns at least this
            fraction of the scoring landmarks that the answer aligns (``RigidEstimate.ambiguity``).
        seed: seed of the hypothesis sampler (deterministic results).
        polish_thresholds_m: association radii of the pose polish after the refinement (step 5 of the module
            docstring); () = none. Chosen on the training splits' unseen sessions among (0.5,), (0.35,),
            (0.5, 0.5), (0.5, 0.5, 0.5) and (0.6, 0.5, 0.4).
        local_search_m: radius (metres) of the local search around the refined answer (step 4b of the module
            docstring); 0 = none. 10 m: two F' cells, the reach of a wrong hypothesis along a corridor.
        local_search_step_m: spacing of the local search's translation grid, metres (half the first refinement
            radius, so that every pose within the radius lies inside some start's basin).
        local_search_starts: distinct grid poses (farther apart than the first refinement radius, and from the
            answer) that are refined.
    """

    top_k_matches: int = 5
    num_hypotheses: int = 4000
    min_pair_separation_m: float = 2.0
    max_length_mismatch_m: float = 3.0
    score_threshold_m: float = 1.5
    score_points: int = 128
    refine_thresholds_m: tuple[float, ...] = (2.0, 1.0, 0.75, 0.75)
    refine_candidates: int = 5
    screen_hypotheses: int = 1500
    screen_source_points: int = 256
    min_inliers: int = 12
    grid_cell_m: float = 0.5
    ambiguity_separation_m: float = 5.0
    ambiguity_separation_rad: float = math.radians(10.0)
    max_ambiguity: float = 1.0
    seed: int = 0
    polish_thresholds_m: tuple[float, ...] = (0.6, 0.5, 0.4)
    local_search_m: float = 10.0
    local_search_step_m: float = 1.0
    local_search_starts: int = 4

    def __post_init__(self) -> None:
        if (self.top_k_matches < 1 or self.num_hypotheses < 1 or self.refine_candidates < 1
                or self.screen_hypotheses < 1 or self.score_points < 2 or self.screen_source_points < 2):
            raise ConfigError("top_k_matches, num_hypotheses, refine_candidates, screen_hypotheses must be >= 1 "
                              "and score_points, screen_source_points >= 2")
        if not self.refine_thresholds_m or min(self.refine_thresholds_m) <= 0:
            raise ConfigError("refine_thresholds_m must be a non-empty sequence of positive radii")
        if any(t <= 0 for t in self.polish_thresholds_m):
            raise ConfigError("polish_thresholds_m must be positive radii")
        if self.grid_cell_m <= 0 or self.score_threshold_m <= 0 or self.min_inliers < 2:
            raise ConfigError("grid_cell_m and score_threshold_m must be positive, min_inliers >= 2")
        if self.local_search_m < 0 or self.local_search_step_m <= 0 or self.local_search_starts < 1:
            raise ConfigError("local_search_m must be >= 0, local_search_step_m > 0 and local_search_starts >= 1")


@dataclass
class LandmarkGrid:
    """Distance (metres) from each grid cell to the nearest landmark, plus a KD-tree of the landmarks (and,
    with the compiled kernels, the landmarks sorted into buckets: ``nearest``).

    Attributes:
        distance_m: (n, n) float32, row = y cell, column = x cell; None for a grid made ``from_within_mask``
            (it answers ``count_within`` at its one threshold only).
        origin_m: coordinate of the grid's lower corner (same for x and y), metres.
        cell_m: cell size, metres.
        tree: KD-tree over the (N, 2) landmark positions.
        points: (N, 2) float64 landmark positions, metres.
    """

    distance_m: np.ndarray | None
    origin_m: float
    cell_m: float
    tree: cKDTree
    points: np.ndarray

    _within: dict[float, np.ndarray] = field(default_factory=dict, repr=False, compare=False)
    _size: int = field(default=0, repr=False, compare=False)
    #: ``buckets()``: built on first use (None then), False when the landmarks cannot be bucketed
    _buckets: LandmarkBuckets | None | bool = field(default=None, repr=False, compare=False)

    @classmethod
    def from_within_mask(cls, packed: np.ndarray, n: int, origin_m: float, cell_m: float, threshold_m: float,
                         points_xy_m: np.ndarray) -> LandmarkGrid:
        """A grid over (M, 2) landmarks from the bit-packed (``np.packbits``, row-major) mask of the n x n cells
        of ``build_landmark_grid(points_xy_m, cell_m)`` closer than ``threshold_m`` to a landmark (e.g. the
        screen's ``ScreenGrid``): no distance transform and no float grid (0.5 MB with 512 landmarks), and it
        counts exactly as the full grid at ``threshold_m`` (same cells, same mask)."""
        pts = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
        grid = cls(None, float(origin_m), float(cell_m), cKDTree(pts), pts, _size=int(n))
        grid._within[threshold_m] = np.append(np.unpackbits(packed, count=n * n), np.uint8(0))
        return grid

    @property
    def size(self) -> int:
        """Cells per side, n."""
        return self._size if self.distance_m is None else int(self.distance_m.shape[0])

    def can_count(self, cell_m: float, threshold_m: float) -> bool:
        """Whether ``count_within(..., threshold_m)`` is available on a grid of ``cell_m`` cells."""
        return self.cell_m == cell_m and (self.distance_m is not None or threshold_m in self._within)

    def within_mask(self, threshold_m: float) -> np.ndarray:
        """(n * n + 1,) uint8: 1 where a cell is closer than ``threshold_m`` to a landmark (row-major), then a
        0 for "outside the grid"; built once per threshold."""
        mask = self._within.get(threshold_m)
        if mask is None:
            if self.distance_m is None:
                raise ConfigError(f"this landmark grid counts within {sorted(self._within)} m only, "
                                  f"not {threshold_m} m")
            mask = np.append((self.distance_m < threshold_m).reshape(-1), False).astype(np.uint8)
            self._within[threshold_m] = mask
        return mask

    def count_within(self, x: np.ndarray, y: np.ndarray, threshold_m: float) -> np.ndarray:
        """Per row of the (V, P) points (x, y): how many are closer than ``threshold_m`` to a landmark -
        exactly ``(lookup(x, y) < threshold_m).sum(axis=1)`` (same cells), without the float look-up."""
        return self._count_within_columns(np.asarray(x).T, np.asarray(y).T, threshold_m)

    def _count_within_columns(self, x: np.ndarray, y: np.ndarray, threshold_m: float) -> np.ndarray:
        """``count_within(x.T, y.T, threshold_m)`` for (P, V) points (column = one hypothesis), exactly (same
        cells), faster: the division by a power-of-two cell is the (exact) multiplication by its inverse,
        and the 0 / 1 hits of fewer than 256 rows are summed without a cast per element."""
        n = self.size
        inv = 1.0 / self.cell_m
        exact = self.cell_m > 0 and math.frexp(self.cell_m)[0] == 0.5 and math.isfinite(inv)
        i = x - self.origin_m
        j = y - self.origin_m
        if exact:
            i *= inv
            j *= inv
        else:
            i /= self.cell_m
            j /= self.cell_m
        i = np.floor(i, out=i).astype(np.int64)
        j = np.floor(j, out=j).astype(np.int64)
        inside = i.view(np.uint64) < np.uint64(n)  # negative cells wrap to huge unsigned values
        inside &= j.view(np.uint64) < np.uint64(n)
        j *= n
        j += i
        np.putmask(j, ~inside, n * n)
        hits = self.within_mask(threshold_m)[j]
        if hits.shape[0] < 256:
            return np.add.reduce(hits, axis=0, dtype=np.uint8).astype(np.int64)
        return hits.sum(axis=0, dtype=np.int64)

    def buckets(self) -> LandmarkBuckets | None:
        """The landmarks sorted into ``_BUCKET_CELL_M`` cells for the compiled nearest-landmark look-up
        (``nearest``), built once (~25 KB for 512 landmarks over ~120 m, at most ~45 KB); None without
        landmarks or with non-finite ones (the KD-tree answers then). Two threads may both build it: the same
        arrays, either one kept."""
        if self._buckets is None:
            m = len(self.points)
            ok = m > 0 and bool(np.all(np.isfinite(self.points)))
            self._buckets = (bucket_landmarks(self.points, _BUCKET_CELL_M, max(_BUCKET_MIN_CELLS, 16 * m))
                             if ok else False)
        return self._buckets if isinstance(self._buckets, LandmarkBuckets) else None

    def nearest(self, xy: np.ndarray, bound_m: float = math.inf) -> tuple[np.ndarray, np.ndarray]:
        """``self.tree.query(xy, distance_upper_bound=bound_m)`` for (K, 2) float64 points (metres), the same
        numbers: (K,) float64 distance (``inf`` for none within the bound) and (K,) int64 landmark index
        (N for none). With the compiled kernels (``reradar_core.jit``) the bucket look-up answers and the tree
        only answers the points it flags (ties, a distance at the bound, non-finite points); else the tree."""
        buckets = self.buckets() if jit_enabled() else None
        if buckets is None or not bound_m > 0:
            return self.tree.query(xy, distance_upper_bound=bound_m)  # type: ignore[no-any-return]
        unbounded = not math.isfinite(bound_m)
        # no bound: search one cell's radius; the nearest within it is the nearest of all, and a point with none
        # within it goes to the tree
        dist, idx, unsure = nearest_within(xy, buckets.cell_m if unbounded else bound_m, buckets, len(self.points))
        if unbounded:
            unsure |= idx == len(self.points)
        ask = np.flatnonzero(unsure)
        if len(ask):  # the tree's answer for a point does not depend on the other points asked with it
            dist[ask], idx[ask] = self.tree.query(np.asarray(xy)[ask], distance_upper_bound=bound_m)
        return dist, idx

    def lookup(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Distance to the nearest landmark at points (x, y) (any shape); far outside the grid = large."""
        if self.distance_m is None:
            raise ConfigError("this landmark grid holds a mask, not distances (made by from_within_mask)")
        n = self.distance_m.shape[0]
        i = np.floor((x - self.origin_m) / self.cell_m).astype(np.int64)
        j = np.floor((y - self.origin_m) / self.cell_m).astype(np.int64)
        inside = (i >= 0) & (i < n) & (j >= 0) & (j < n)
        d = self.distance_m[np.clip(j, 0, n - 1), np.clip(i, 0, n - 1)]
        return np.where(inside, d, np.float32(1e9))


#: smallest side of the buckets of ``LandmarkGrid.nearest``, metres: the largest default association radius
#: (``refine_thresholds_m``), the fastest side measured (``nn_kernels.bucket_landmarks``; any side gives the
#: same answers)
_BUCKET_CELL_M = 2.0
#: cells a bucket grid may have regardless of the number of landmarks (16 per landmark above that; 4 bytes
#: each, so 32 KB with 512 landmarks): 2 m cells over up to ~180 x 180 m
_BUCKET_MIN_CELLS = 8192


def build_landmark_grid(points_xy_m: np.ndarray, cell_m: float = 0.5, margin_m: float = 5.0) -> LandmarkGrid:
    """Distance-transform grid of (N, 2) landmark positions (metres) covering them plus ``margin_m``."""
    pts = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
    half = float(np.max(np.abs(pts))) + margin_m if len(pts) else margin_m
    n = max(2, int(math.ceil(2 * half / cell_m)))
    occ = np.full((n, n), 255, np.uint8)
    ij = np.floor((pts + half) / cell_m).astype(np.int64)
    ok = (ij >= 0).all(axis=1) & (ij < n).all(axis=1)
    occ[ij[ok, 1], ij[ok, 0]] = 0
    dist = cv2.distanceTransform(occ, cv2.DIST_L2, cv2.DIST_MASK_PRECISE).astype(np.float32) * cell_m
    return LandmarkGrid(dist, -half, cell_m, cKDTree(pts), pts)


def topk_last_axis(scores: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` largest entries along the last axis of float ``scores`` (any leading shape), in
    exactly the order ``torch.topk(scores, k, dim=-1, sorted=False)`` returns them - the order the seeded
    minimal-set draws index, so the answers depend on it. ``scores`` is used as scratch space (overwritten)
    when C-contiguous, else copied.

    torch's CPU kernel copies every row into a (value, index) vector and ``std::partial_sort`` s it when
    ``64 k <= n`` (then its "unsorted" output is in descending order; ties in an order of its heap's making);
    that costs ~3 us per row. Here ``k + 1`` vectorised ``argmax`` passes give the same indices for every row
    whose ``k + 1`` largest values are distinct and not NaN (~6x faster on the screen's 5,120 rows of 512);
    the other rows, and shapes where torch selects with ``nth_element`` instead, go to ``torch.topk``.
    """
    n = scores.shape[-1]
    lead = scores.shape[:-1]
    k = min(k, n)
    if k < 1 or 64 * k > n:
        import torch  # loaded anyway by the model; its kernel is the reference for ties

        return torch.topk(torch.from_numpy(scores), k, dim=-1, sorted=False).indices.numpy()
    flat = np.ascontiguousarray(scores.reshape(-1, n))  # a view when contiguous, else a copy: scratch either way
    rows = flat.shape[0]
    cells = flat.reshape(-1)  # a view of flat: the passes below read and write entries by flat index
    start = np.arange(0, rows * n, n)
    idx = np.empty((k + 1, rows), np.int64)  # pass-major, so each pass writes contiguous rows
    val = np.empty((k + 1, rows), flat.dtype)
    for j in range(k + 1):
        i = flat.argmax(axis=1)
        idx[j] = i
        i += start
        np.take(cells, i, out=val[j])
        cells[i] = -np.inf
    unclear = np.isnan(val[0])
    for j in range(k):
        unclear |= val[j] == val[j + 1]
        unclear |= np.isnan(val[j + 1])
    unclear = np.flatnonzero(unclear)
    out = np.ascontiguousarray(idx[:k].T)
    if len(unclear):  # ties or NaN: restore those rows and let torch order them as it does
        import torch

        for j in reversed(range(k + 1)):  # last pass first: a pass over an all -inf rest may re-pick an index
            flat[unclear, idx[j, unclear]] = val[j, unclear]
        out[unclear] = torch.topk(torch.from_numpy(np.ascontiguousarray(flat[unclear])), k, dim=1,
                                  sorted=False).indices.numpy()
    return out.reshape(*lead, k)


def _topk_pairs(desc_src: np.ndarray, desc_dst: np.ndarray, k: int) -> np.ndarray:
    """(N*k, 2) index pairs: each source row with its k most cosine-similar destination rows."""
    sim = desc_src.astype(np.float32) @ desc_dst.astype(np.float32).T
    k = min(k, sim.shape[1])
    idx = topk_last_axis(sim, k)
    return np.stack([np.repeat(np.arange(sim.shape[0]), k), idx.reshape(-1)], axis=1)


def _hypotheses(src: np.ndarray, dst: np.ndarray, pairs: np.ndarray, cfg: AlignmentConfig,
                rng: np.random.Generator) -> np.ndarray:
    """(V, 3) poses (x, y, yaw) of the length-consistent minimal sets among ``cfg.num_hypotheses`` seeded
    draws of two (P, 2) index pairs (source row, destination row) into the (N, 2) / (M, 2) float64 landmarks.
    Coordinates are gathered as contiguous x / y arrays (the same numbers as gathering rows)."""
    a = rng.integers(0, len(pairs), cfg.num_hypotheses)
    b = rng.integers(0, len(pairs), cfg.num_hypotheses)
    ps, pd = np.ascontiguousarray(pairs[:, 0]), np.ascontiguousarray(pairs[:, 1])
    sx, sy = np.ascontiguousarray(src[:, 0]), np.ascontiguousarray(src[:, 1])
    dx, dy = np.ascontiguousarray(dst[:, 0]), np.ascontiguousarray(dst[:, 1])
    i1, i2, j1, j2 = ps[a], ps[b], pd[a], pd[b]
    vsx, vsy = sx[i2] - sx[i1], sy[i2] - sy[i1]
    vdx, vdy = dx[j2] - dx[j1], dy[j2] - dy[j1]
    ls, ld = np.hypot(vsx, vsy), np.hypot(vdx, vdy)
    ok = np.flatnonzero((ls > cfg.min_pair_separation_m) & (np.abs(ls - ld) < cfg.max_length_mismatch_m))
    # solve only the consistent sets (~1 in 10): element-wise, so the same poses as solving all, then filtering
    i1, i2, j1, j2 = i1[ok], i2[ok], j1[ok], j2[ok]
    yaw = np.arctan2(vdy[ok], vdx[ok]) - np.arctan2(vsy[ok], vsx[ok])
    c, s = np.cos(yaw), np.sin(yaw)
    msx, msy = (sx[i1] + sx[i2]) / 2, (sy[i1] + sy[i2]) / 2  # midpoints: the rotation about them is best
    mdx, mdy = (dx[j1] + dx[j2]) / 2, (dy[j1] + dy[j2]) / 2  # conditioned
    tx = mdx - (c * msx - s * msy)
    ty = mdy - (s * msx + c * msy)
    return np.stack([tx, ty, yaw], axis=1)


#: hypotheses scored at once, so the (128, block) temporaries stay in the CPU cache
_SCORE_BLOCK = 512


def _score(poses: np.ndarray, src: np.ndarray, grid: LandmarkGrid, threshold_m: float) -> np.ndarray:
    """Source landmarks within ``threshold_m`` of a destination landmark under each pose (element-wise
    arithmetic in blocks of poses: the counts do not depend on the block size, nor on the layout)."""
    if jit_enabled() and grid.size > 0:  # one compiled loop, the same arithmetic (``matching.kernels``)
        inv = 1.0 / grid.cell_m
        exact = grid.cell_m > 0 and math.frexp(grid.cell_m)[0] == 0.5 and math.isfinite(inv)
        return count_aligned_pose(np.ascontiguousarray(src[:, 0]), np.ascontiguousarray(src[:, 1]),
                                  np.cos(poses[:, 2]), np.sin(poses[:, 2]), np.ascontiguousarray(poses[:, 0]),
                                  np.ascontiguousarray(poses[:, 1]), grid.origin_m, inv if exact else grid.cell_m,
                                  exact, grid.size, grid.within_mask(threshold_m))
    out = np.empty(len(poses), np.int64)
    sx, sy = src[:, 0:1], src[:, 1:2]
    for lo in range(0, len(poses), _SCORE_BLOCK):
        p = poses[lo:lo + _SCORE_BLOCK]
        c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
        # (P, V): one column per pose, so the per-pose operands broadcast along long rows (fast)
        x = c * sx - s * sy + p[:, 0]
        y = s * sx + c * sy + p[:, 1]
        out[lo:lo + _SCORE_BLOCK] = grid._count_within_columns(x, y, threshold_m)
    return out


def count_aligned(poses: np.ndarray, points_src: np.ndarray, grid: LandmarkGrid, threshold_m: float) -> np.ndarray:
    """How many of the (N, 2) source landmarks (metres, source frame) land within ``threshold_m`` of one of
    ``grid``'s landmarks under each of the (P, 3) poses (x m, y m, yaw rad; source -> grid frame): (P,) int64,
    the hypotheses' score (``grid`` must count at ``threshold_m``: ``LandmarkGrid.within_mask``)."""
    poses = np.asarray(poses, np.float64).reshape(-1, 3)
    return _score(poses, np.asarray(points_src, np.float64).reshape(-1, 2), grid, threshold_m)


def _apply(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 2) ``points`` moved by ``pose`` (x, y, yaw): x c - y s + x0, x s + y c + y0, element-wise (the
    compiled refinement does the same operations, ``nn_kernels.refine_poses``)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    x, y = points[:, 0], points[:, 1]
    out = np.empty((len(points), 2))
    out[:, 0] = c * x - s * y + pose[0]
    out[:, 1] = s * x + c * y + pose[1]
    return out


def _apply_all(poses: list[np.ndarray], points: np.ndarray) -> np.ndarray:
    """``np.stack([_apply(p, points) for p in poses])``, (H, N, 2), exactly (the same element-wise operations
    with the same ``math.cos`` / ``math.sin`` values, broadcast over the poses)."""
    cs = np.array([[math.cos(p[2]), math.sin(p[2]), p[0], p[1]] for p in poses]).reshape(-1, 4)
    c, s, x0, y0 = (cs[:, i:i + 1] for i in range(4))  # (H, 1) each
    x, y = points[:, 0], points[:, 1]
    out = np.empty((len(poses), len(points), 2))
    out[..., 0] = c * x - s * y + x0
    out[..., 1] = s * x + c * y + y0
    return out


def refine_pose(src: np.ndarray, grid: LandmarkGrid, pose: np.ndarray,
            thresholds: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Refine the (3,) pose T_dst_src (x m, y m, yaw rad) of the (N, 2) source landmarks against ``grid``'s by
    iterated nearest-landmark association within each of the shrinking ``thresholds`` (metres) and a
    least-squares fit per step (stopping when fewer than 3 associate): the refined (3,) pose (yaw not wrapped)
    and the (N,) bool mask of the last association. The reference of ``_refine_all``; tracking's registration."""
    buckets = grid.buckets() if jit_enabled() and thresholds else None
    if buckets is not None:  # compiled (``nn_kernels.refine_poses``), the same numbers
        poses, masks, unsure = refine_poses(src, np.asarray(pose, np.float64)[None], thresholds, grid.points,
                                            buckets)
        if not unsure[0]:
            return poses[0], masks[0]
    mask = np.zeros(len(src), dtype=bool)
    for thr in thresholds:
        dist, nn = grid.nearest(_apply(pose, src), thr)
        mask = np.isfinite(dist)
        if mask.sum() < 3:
            return pose, mask
        pose = fit_rigid_2d(src[mask], grid.points[nn[mask]])
    return pose, mask


#: slack on the skip test of ``_refine_all``, metres: far above the rounding of positions and distances
#: (~1e-14 m at map scale)
_SKIP_SLACK_M = 1e-6


def _refine_all(src: np.ndarray, grid: LandmarkGrid, poses: list[np.ndarray],
                thresholds: tuple[float, ...]) -> list[tuple[np.ndarray, np.ndarray]]:
    """``[refine_pose(src, grid, p, thresholds) for p in poses]``, exactly (same pose bits, same masks), faster:

    - each iteration's nearest-landmark look-ups of all still-refining hypotheses go to the KD-tree in one
      call (~13 us of overhead per call; the tree's answer for a point does not depend on the other points);
    - every look-up tells how far the nearest destination landmark was from the point's position then (its
      distance, or at least the radius when none was within it). A point that has moved by ``d`` since is
      at least that minus ``d`` from every landmark now, so when that exceeds the new radius (plus a rounding
      slack) its look-up is skipped: the tree would answer "none" too;
    - the landmarks of all hypotheses move at once (``_apply_all``) and each hypothesis is fitted by
      ``fit_rigid_2d``;
    - with the compiled kernels the whole loop runs compiled (``nn_kernels.refine_poses``: bucket look-ups,
      the same fit's operations in the same order), and the KD-tree path only for a hypothesis whose look-ups
      hit a tie or a distance at a radius.

    Args: (N, 2) float64 ``src``; (3,) float64 poses; the association radii (metres).
    Returns: per pose, the refined (3,) pose and the (N,) bool mask of the last association.
    """
    n = len(src)
    buckets = grid.buckets() if jit_enabled() and poses and thresholds else None
    if buckets is not None:  # compiled (``nn_kernels.refine_poses``); a hypothesis it is unsure of: the tree
        refined, masks, unsure = refine_poses(src, np.stack(poses), thresholds, grid.points, buckets)
        return [refine_pose(src, grid, poses[h], thresholds) if unsure[h] else (refined[h], masks[h])
                for h in range(len(poses))]
    out: list[tuple[np.ndarray, np.ndarray]] = [(p, np.zeros(n, dtype=bool)) for p in poses]
    active = list(range(len(poses)))
    current = list(poses)
    # per point of each refining hypothesis: where it was last looked up, and a lower bound on its distance
    # to the nearest destination landmark there (metres; nothing known before the first look-up)
    seen_xy = np.zeros((len(poses), n, 2))
    seen_m = np.full((len(poses), n), -np.inf)
    for it, thr in enumerate(thresholds):
        if not active:
            break
        xy = _apply_all([current[h] for h in active], src)  # (A, N, 2)
        ask = None  # all points
        if it:
            moved = xy - seen_xy
            ask = ~(seen_m - np.hypot(moved[..., 0], moved[..., 1]) > thr + _SKIP_SLACK_M)  # NaN: asked
            if ask.all():
                ask = None
        if ask is None:
            dist, nn = grid.nearest(xy.reshape(-1, 2), thr)
            dist, nn = dist.reshape(len(active), n), nn.reshape(len(active), n)
            found = np.isfinite(dist)
            seen_xy, seen_m = xy, np.where(found, dist, thr)
        else:
            sel = np.flatnonzero(ask)
            dist, idx = grid.tree.query(xy.reshape(-1, 2)[sel], distance_upper_bound=thr)
            found = np.zeros((len(active), n), dtype=bool)
            nn = np.zeros((len(active), n), dtype=np.intp)
            hit = np.isfinite(dist)
            found.reshape(-1)[sel] = hit
            nn.reshape(-1)[sel] = idx
            np.copyto(seen_xy, xy, where=ask[..., None])  # seen_xy is this loop's own array
            seen_m.reshape(-1)[sel] = np.where(hit, dist, thr)
        rows = []
        for row, h in enumerate(active):
            mask = found[row].copy()
            if np.count_nonzero(mask) < 3:
                out[h] = (current[h], mask)
                continue
            current[h] = fit_rigid_2d(src[mask], grid.points[nn[row][mask]])
            out[h] = (current[h], mask)
            rows.append(row)
        active = [active[r] for r in rows]
        seen_xy, seen_m = seen_xy[rows], seen_m[rows]
    return out


def screen_alignment(points_src: np.ndarray, desc_src: np.ndarray, points_dst: np.ndarray,
                     desc_dst: np.ndarray, config: AlignmentConfig = AlignmentConfig(),
                     grid: LandmarkGrid | None = None) -> float:
    """Cheap alignment score of two landmark sets: steps 1-3 of ``estimate_pose_guided`` without refinement.

    Uses ``screen_source_points`` source landmarks for descriptor pairing and ``screen_hypotheses`` minimal
    sets; returns the best hypothesis' fraction of (``score_points`` subsampled) source landmarks within
    ``score_threshold_m`` of a destination landmark, in [0, 1] (0 for degenerate input). Used to re-rank
    many retrieved keyframes before the full estimator runs on the best few (``localization.localize``).
    Arguments as ``estimate_pose_guided``.
    """
    src = np.asarray(points_src, dtype=np.float64).reshape(-1, 2)
    dst = np.asarray(points_dst, dtype=np.float64).reshape(-1, 2)
    n = len(src)
    if n < 2 or len(dst) < 2 or not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        return 0.0
    if desc_src.shape[0] != n or desc_dst.shape[0] != len(dst) or desc_src.shape[1] != desc_dst.shape[1]:
        raise ConfigError(f"descriptor shapes {desc_src.shape}, {desc_dst.shape} do not match the landmarks")
    if grid is None or not grid.can_count(config.grid_cell_m, config.score_threshold_m):  # else rebuilt
        grid = build_landmark_grid(dst, config.grid_cell_m)
    sub = np.arange(0, n, max(1, n // config.screen_source_points))
    pairs = _topk_pairs(desc_src[sub], desc_dst, config.top_k_matches)
    pairs[:, 0] = sub[pairs[:, 0]]
    rng = np.random.default_rng(config.seed)
    cfg = replace(config, num_hypotheses=config.screen_hypotheses)
    hyp = _hypotheses(src, dst, pairs, cfg, rng)
    if len(hyp) == 0:
        return 0.0
    scored = src[:: max(1, n // config.score_points)]
    return float(_score(hyp, scored, grid, config.score_threshold_m).max() / len(scored))


def estimate_pose_guided(points_src: np.ndarray, desc_src: np.ndarray, points_dst: np.ndarray,
                         desc_dst: np.ndarray, config: AlignmentConfig = AlignmentConfig(),
                         grid: LandmarkGrid | None = None) -> RigidEstimate:
    """Estimate T_dst_src from two landmark sets with local descriptors (method in the module docstring).

    Args:
        points_src: (N, 2) source landmarks, metres (the query scan's sensor frame).
        desc_src: (N, C) source local descriptors (L2-normalised rows, any float dtype).
        points_dst: (M, 2) destination landmarks, metres (the keyframe's sensor frame).
        desc_dst: (M, C) destination local descriptors.
        config: settings.
        grid: ``build_landmark_grid(points_dst)`` if already computed (e.g. cached per keyframe).

    Returns:
        ``RigidEstimate`` with ``pose`` = T_dst_src (x m, y m, yaw rad), ``num_inliers`` = source landmarks
        within the final association radius of a destination landmark, ``inlier_ratio`` = that / N and
        ``inlier_mask`` over the source landmarks. Never raises on degenerate input: ``success`` is False
        with a ``reason``.
    """
    src = np.asarray(points_src, dtype=np.float64).reshape(-1, 2)
    dst = np.asarray(points_dst, dtype=np.float64).reshape(-1, 2)
    n = len(src)
    empty = np.zeros(n, dtype=bool)

    def fail(reason: str, pose: np.ndarray | None = None, mask: np.ndarray = empty) -> RigidEstimate:
        k = int(mask.sum())
        return RigidEstimate(False, np.full(3, np.nan) if pose is None else pose, k, k / n if n else 0.0,
                             mask, reason)

    if n < 2 or len(dst) < 2:
        return fail("too_few_landmarks")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        return fail("non_finite_input")
    if desc_src.shape[0] != n or desc_dst.shape[0] != len(dst) or desc_src.shape[1] != desc_dst.shape[1]:
        raise ConfigError(f"descriptor shapes {desc_src.shape}, {desc_dst.shape} do not match the landmarks")
    if grid is None or not grid.can_count(config.grid_cell_m, config.score_threshold_m):  # else rebuilt
        grid = build_landmark_grid(dst, config.grid_cell_m)
    rng = np.random.default_rng(config.seed)
    hyp = _hypotheses(src, dst, _topk_pairs(desc_src, desc_dst, config.top_k_matches), config, rng)
    if len(hyp) == 0:
        return fail("no_consistent_hypothesis")
    step = max(1, n // config.score_points)
    scores = _score(hyp, src[::step], grid, config.score_threshold_m)
    best = np.argsort(-scores, kind="stable")[: config.refine_candidates]
    refined = _refine_all(src, grid, [hyp[h] for h in best], config.refine_thresholds_m)
    pose, best_mask = max(refined, key=lambda r: int(r[1].sum()))  # first of equals: best-scored hypothesis
    hypothesis_answer = None  # the hypotheses' own answer, kept when the local search moves away from it
    if config.local_search_m > 0 and int(best_mask.sum()) >= 3:
        starts = _local_starts(pose, src[::step], grid, config)
        if len(starts):
            found = _refine_all(src, grid, list(starts), config.refine_thresholds_m)
            other, other_mask = max(found, key=lambda r: int(r[1].sum()))
            if int(other_mask.sum()) > int(best_mask.sum()):  # the answer only moves for more aligned landmarks
                hypothesis_answer = pose
                pose, best_mask = other, other_mask
    best_pose = _polished(src, grid, pose, best_mask, config)
    k = int(best_mask.sum())
    if k < config.min_inliers:
        return fail("too_few_inliers", best_pose, best_mask)
    # The ambiguity is the hypothesis search's: measured around the answer the hypotheses gave, also when the
    # local search moved it. A pose found only by the local search is as doubtful as the search that missed it
    # (a periodic scene stays refused), and the refined starts are not rivals: they are the answer's own
    # neighbourhood along a corridor (counting them cost 4 correct answers of 11,202 runs on the training splits,
    # docs/BENCHMARKS.md "Session 13").
    around = best_pose if hypothesis_answer is None else _polished(src, grid, hypothesis_answer, best_mask, config)
    ambiguity = _ambiguity(around, hyp, scores, src[::step], grid, config)
    if ambiguity >= config.max_ambiguity:
        est = fail("ambiguous", best_pose, best_mask)
        est.ambiguity = ambiguity
        return est
    residual, _ = grid.nearest(_apply(best_pose, src[best_mask]))
    return RigidEstimate(True, best_pose, k, k / n, best_mask, None, len(hyp), float(np.sqrt(np.mean(residual**2))),
                         ambiguity)


def _polished(src: np.ndarray, grid: LandmarkGrid, pose: np.ndarray, mask: np.ndarray,
              config: AlignmentConfig) -> np.ndarray:
    """Step 5: ``pose`` refined at the polish radii (when at least 3 landmarks associated), yaw wrapped. The
    polish's own association mask is not the count's."""
    if int(mask.sum()) >= 3:
        pose, _ = refine_pose(src, grid, pose, config.polish_thresholds_m)
    return np.array([pose[0], pose[1], wrap_angle(pose[2])])


def _local_starts(pose: np.ndarray, scored: np.ndarray, grid: LandmarkGrid, config: AlignmentConfig) -> np.ndarray:
    """(S, 3) starting poses of the local search around the refined ``pose`` (x m, y m, yaw rad): the translation
    grid within ``local_search_m`` at ``local_search_step_m``, ``pose``'s heading, scored like the hypotheses,
    and greedily the best ``local_search_starts`` that lie farther than the first refinement radius from the
    answer and from each other (nearer ones fall into a basin already refined). Why: the hypotheses come from
    descriptor pairs, and when a query is far (15 m and more) from the keyframe few true pairs remain, so every
    refined hypothesis can sit at a wrong place along a corridor whose walls align at any shift (a real Oxford
    pair 15.4 m apart: all hypotheses 4-20 m off, the true pose aligning 252 landmarks to the answer's 211)."""
    r, h = config.local_search_m, config.local_search_step_m
    o = np.arange(-math.floor(r / h), math.floor(r / h) + 1) * h
    ox, oy = np.meshgrid(o, o)
    ox, oy = ox.ravel(), oy.ravel()
    sep = config.refine_thresholds_m[0]
    keep = (np.hypot(ox, oy) <= r) & (np.hypot(ox, oy) > sep)
    cand = np.stack([pose[0] + ox[keep], pose[1] + oy[keep], np.full(int(keep.sum()), pose[2])], axis=1)
    if len(cand) == 0:
        return cand
    order = np.argsort(-_score(cand, scored, grid, config.score_threshold_m), kind="stable")
    picked: list[int] = []
    for i in order:
        if all(math.hypot(cand[i, 0] - cand[j, 0], cand[i, 1] - cand[j, 1]) > sep for j in picked):
            picked.append(int(i))
            if len(picked) == config.local_search_starts:
                break
    return cand[picked]


def _ambiguity(pose: np.ndarray, hyp: np.ndarray, scores: np.ndarray, scored: np.ndarray, grid: LandmarkGrid,
               config: AlignmentConfig) -> float:
    """Best rival hypothesis score / the answer's score on the same landmarks (0 = unique, >= 1 = a tie).

    A rival is a hypothesis farther than ``ambiguity_separation_m`` or ``ambiguity_separation_rad`` from
    ``pose``: along a straight façade or in a repeated structure a second, distinct pose aligns almost as many
    landmarks, and picking either is a guess.
    """
    own = float(_score(pose[None], scored, grid, config.score_threshold_m)[0])
    far = ((np.hypot(hyp[:, 0] - pose[0], hyp[:, 1] - pose[1]) > config.ambiguity_separation_m)
           | (np.abs(wrap_angle(hyp[:, 2] - pose[2])) > config.ambiguity_separation_rad))
    if not far.any() or own <= 0:
        return 0.0 if own > 0 else float("inf")
    return float(scores[far].max()) / own
