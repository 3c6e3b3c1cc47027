"""Nearest-landmark look-ups within a radius over a uniform bucket grid: the compiled replacement of
``cKDTree.query(points, distance_upper_bound=r)`` in the guided pose estimate (``matching.alignment``).

The refinement asks ~2,500 points per call for their nearest keyframe landmark within 2 m, 1 m or 0.75 m. With
the landmarks sorted into 2 m cells, a point's candidates are those of the 2-9 cells its search square touches
(smoke suite, 512 landmarks per keyframe: ~7.5 candidates at 0.75 m, ~15 at 2 m): a few distance evaluations,
~40 ns a point, instead of a KD-tree descent with a heap per point (~200 ns).

The answers are the tree's, number for number:

- the squared distance is computed as scipy does (``dx * dx + dy * dy``, landmark minus point, no fused
  multiply-add) and compared strictly below the squared bound (``bound * bound``), as scipy does; the distance
  returned is its square root;
- where the tree's answer could depend on its traversal order or on its own rounding - two candidates at
  (almost) the same squared distance, or a candidate (almost) at the bound - and for non-finite points (the
  tree raises), the kernel flags the point instead of answering, and the caller asks the tree for those.
  Within ``TIE_BAND_M2`` counts as "almost": far above the rounding of squared distances at map scale
  (~1e-13 m^2) and far below anything that happens by chance (a band ~1e-9 m wide around each radius).

Kernels are decorated with ``reradar_core.jit.njit``; callers run them only when ``jit_enabled()``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from reradar_core.jit import njit

__all__ = ["TIE_BAND_M2", "LandmarkBuckets", "bucket_landmarks", "nearest_within", "refine_poses"]

#: squared metres: candidates whose squared distances differ by at most this (or lie this close to the squared
#: bound) are a "tie"; the point is left to the KD-tree
TIE_BAND_M2 = 1e-9

#: widening of the search square beyond the bound, relative to the coordinates' magnitude: the square is
#: computed in rounded arithmetic and must contain every landmark the exact comparison could accept (the
#: rounding is ~1e-16 relative; this is 1e-9)
_REACH_SLACK = 1e-9


@dataclass(frozen=True)
class LandmarkBuckets:
    """Landmarks sorted by the cell of a uniform grid (compressed rows: cell ``c`` holds the sorted entries
    ``starts[c]:starts[c + 1]``).

    Attributes:
        origin_x, origin_y: lower corner of cell (0, 0), metres (the landmarks' minimum coordinates).
        cell_m: cell side, metres.
        inv_cell: 1 / cell_m; a coordinate v lies in cell ``floor((v - origin) * inv_cell)`` (clipped).
        extent_m: largest absolute landmark coordinate, metres (scales the search square's rounding slack).
        nx, ny: cells along x and y; cell (i, j) has the flat number ``j * nx + i``.
        starts: (nx * ny + 1,) int32, first sorted entry of each cell, then the number of landmarks.
        order: (M,) int32, original landmark index of each sorted entry.
        xs, ys: (M,) float64, coordinates of the sorted entries (contiguous copies, so a cell's candidates
            are read from consecutive memory), metres.
    """

    origin_x: float
    origin_y: float
    cell_m: float
    inv_cell: float
    extent_m: float
    nx: int
    ny: int
    starts: np.ndarray
    order: np.ndarray
    xs: np.ndarray
    ys: np.ndarray

    @property
    def nbytes(self) -> int:
        return int(self.starts.nbytes + self.order.nbytes + self.xs.nbytes + self.ys.nbytes)


def bucket_landmarks(points: np.ndarray, cell_m: float, max_cells: int) -> LandmarkBuckets:
    """Sort (M, 2) float64 finite landmark positions (metres, M >= 1) into cells of ``cell_m`` metres or
    larger: the side grows when the landmarks' bounding box would need more than ``max_cells`` cells (memory:
    4 bytes per cell). Any side gives the same look-up answers, only the speed differs: the search square of a
    radius r spans up to ``ceil(2 r / side) + 1`` cells per axis, and each holds more landmarks as the side
    grows (measured on the smoke suite's keyframes, 512 landmarks over ~120 m: 1.5 m 46 ns a point, 2 m 39 ns,
    3 m 41 ns, 4 m 43 ns)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    lo = pts.min(axis=0)
    span = pts.max(axis=0) - lo
    side = float(cell_m)
    # cells over the bounding box, (span / side + 1) per axis; widen the side until they fit the cap
    while (span[0] // side + 1) * (span[1] // side + 1) > max_cells:
        side *= 1.25
    nx, ny = int(span[0] // side) + 1, int(span[1] // side) + 1
    inv = 1.0 / side
    # the cell of a coordinate is computed exactly as the kernel computes the search square's corners (same
    # operations, each monotonic in the coordinate, so a landmark inside the square is in one of its cells),
    # clipped so that the largest coordinate stays in the last cell whatever the rounding
    ix = np.clip(np.floor((pts[:, 0] - lo[0]) * inv), 0, nx - 1).astype(np.int64)
    iy = np.clip(np.floor((pts[:, 1] - lo[1]) * inv), 0, ny - 1).astype(np.int64)
    key = iy * nx + ix
    order = np.argsort(key, kind="stable")
    starts = np.zeros(nx * ny + 1, dtype=np.int64)
    np.cumsum(np.bincount(key, minlength=nx * ny), out=starts[1:])
    return LandmarkBuckets(float(lo[0]), float(lo[1]), side, inv, float(np.abs(pts).max()), nx, ny,
                           starts.astype(np.int32), order.astype(np.int32),
                           np.ascontiguousarray(pts[order, 0]), np.ascontiguousarray(pts[order, 1]))


@njit
def _nearest_point(x: float, y: float, ub: float, reach: float, origin_x: float, origin_y: float,
                   inv_cell: float, nx: int, ny: int, starts: np.ndarray, xs: np.ndarray, ys: np.ndarray,
                   tie_m2: float) -> tuple[float, int, bool]:  # pragma: no cover - compiled
    """One point's look-up: (smallest squared distance, its sorted entry or -1, unsure) among the landmarks
    of the cells the search square (half side ``reach``) touches; ``ub`` is the squared bound."""
    if not (math.isfinite(x) and math.isfinite(y)):
        return np.inf, -1, True  # the tree raises on these: let it
    # search square in cell units, kept as floats (np.floor) and compared before any integer cast, so a
    # point far away cannot overflow the cast
    fx0 = np.floor((x - reach - origin_x) * inv_cell)
    fx1 = np.floor((x + reach - origin_x) * inv_cell)
    fy0 = np.floor((y - reach - origin_y) * inv_cell)
    fy1 = np.floor((y + reach - origin_y) * inv_cell)
    if fx1 < 0 or fy1 < 0 or fx0 > nx - 1 or fy0 > ny - 1:
        return np.inf, -1, False  # square outside the bucket grid: no landmark within the bound
    i0 = int(max(fx0, 0.0))
    i1 = int(min(fx1, nx - 1.0))
    j0 = int(max(fy0, 0.0))
    j1 = int(min(fy1, ny - 1.0))
    best = np.inf  # smallest and second smallest squared distance among the candidates
    second = np.inf
    best_at = -1
    edge = False  # a candidate (almost) at the bound
    for j in range(j0, j1 + 1):
        row = j * nx
        # the cells i0..i1 of a row are consecutive in the sorted entries
        for e in range(starts[row + i0], starts[row + i1 + 1]):
            dx = xs[e] - x
            dy = ys[e] - y
            d2 = dx * dx + dy * dy
            # selects instead of branches: which candidate is nearest is unpredictable, and a
            # mispredicted branch per candidate cost ~40 % of the time
            edge |= abs(d2 - ub) <= tie_m2
            hi = d2 if d2 > best else best
            second = hi if hi < second else second  # second smallest of (best, second, d2)
            best_at = e if d2 < best else best_at
            best = d2 if d2 < best else best
    unsure = edge or (best < ub and second - best <= tie_m2)
    return best, best_at, unsure


@njit
def _reach(bound_m: float, extent_m: float) -> float:  # pragma: no cover - compiled
    """Half side of the search square: only a point within the bound of a landmark (|x| <= extent + bound)
    can find one, and for those the rounding of the square's corners is far below this slack; farther points
    find none either way."""
    return bound_m + _REACH_SLACK * (1.0 + extent_m + 2.0 * bound_m)


@njit
def _nearest_within_kernel(xy: np.ndarray, bound_m: float, origin_x: float, origin_y: float, inv_cell: float,
                           extent_m: float, nx: int, ny: int, starts: np.ndarray, order: np.ndarray,
                           xs: np.ndarray, ys: np.ndarray, num_landmarks: int,
                           tie_m2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """Loop of ``nearest_within`` (arguments: the buckets' fields, unpacked for numba)."""
    k = xy.shape[0]
    dist = np.full(k, np.inf)
    idx = np.full(k, num_landmarks, dtype=np.int64)
    unsure = np.zeros(k, dtype=np.bool_)
    ub = bound_m * bound_m  # scipy squares the bound the same way and compares squared distances to it
    reach = _reach(bound_m, extent_m)
    for p in range(k):
        best, best_at, flag = _nearest_point(xy[p, 0], xy[p, 1], ub, reach, origin_x, origin_y, inv_cell, nx,
                                             ny, starts, xs, ys, tie_m2)
        if flag:
            unsure[p] = True
        elif best < ub:
            dist[p] = math.sqrt(best)
            idx[p] = order[best_at]
    return dist, idx, unsure


@njit
def _refine_kernel(src: np.ndarray, poses: np.ndarray, thresholds: np.ndarray, points: np.ndarray,
                   origin_x: float, origin_y: float, inv_cell: float, extent_m: float, nx: int, ny: int,
                   starts: np.ndarray, order: np.ndarray, xs: np.ndarray, ys: np.ndarray,
                   tie_m2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """Loop of ``refine_poses`` (arguments: the buckets' fields, unpacked for numba)."""
    num_h, n = poses.shape[0], src.shape[0]
    out = poses.copy()
    masks = np.zeros((num_h, n), np.bool_)
    unsure = np.zeros(num_h, np.bool_)
    mx = np.empty(n)  # the associated pairs of one step, in source order (as boolean indexing takes them)
    my = np.empty(n)
    dx = np.empty(n)
    dy = np.empty(n)
    for h in range(num_h):
        tx, ty, yaw = poses[h, 0], poses[h, 1], poses[h, 2]
        for t in range(thresholds.shape[0]):
            bound = thresholds[t]
            ub = bound * bound
            reach = _reach(bound, extent_m)
            c, s = math.cos(yaw), math.sin(yaw)
            k = 0
            for p in range(n):
                x = c * src[p, 0] - s * src[p, 1] + tx  # ``alignment._apply``
                y = s * src[p, 0] + c * src[p, 1] + ty
                best, best_at, flag = _nearest_point(x, y, ub, reach, origin_x, origin_y, inv_cell, nx, ny,
                                                     starts, xs, ys, tie_m2)
                if flag:
                    unsure[h] = True
                    break
                found = best < ub
                masks[h, p] = found
                if found:
                    q = order[best_at]
                    mx[k], my[k], dx[k], dy[k] = src[p, 0], src[p, 1], points[q, 0], points[q, 1]
                    k += 1
            if unsure[h] or k < 3:
                break
            # ``ransac.fit_rigid_2d`` (unweighted): every sum left to right
            ms0, ms1, md0, md1 = mx[0], my[0], dx[0], dy[0]
            for i in range(1, k):
                ms0 += mx[i]
                ms1 += my[i]
                md0 += dx[i]
                md1 += dy[i]
            ms0, ms1, md0, md1 = ms0 / k, ms1 / k, md0 / k, md1 / k
            cross = 0.0
            dot = 0.0
            for i in range(k):
                a0, a1 = mx[i] - ms0, my[i] - ms1
                b0, b1 = dx[i] - md0, dy[i] - md1
                cr = a0 * b1 - a1 * b0
                dt = a0 * b0 + a1 * b1
                if i == 0:
                    cross, dot = cr, dt
                else:
                    cross += cr
                    dot += dt
            yaw = math.atan2(cross, dot)
            c, s = math.cos(yaw), math.sin(yaw)
            tx = md0 - (c * ms0 - s * ms1)
            ty = md1 - (s * ms0 + c * ms1)
        out[h, 0], out[h, 1], out[h, 2] = tx, ty, yaw
    return out, masks, unsure


def refine_poses(src: np.ndarray, poses: np.ndarray, thresholds: tuple[float, ...], points: np.ndarray,
                 buckets: LandmarkBuckets) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``alignment.refine_pose`` of every pose at once: iterated association of the (N, 2) float64 source points
    (metres) with their nearest of the (M, 2) ``points`` within each radius of ``thresholds`` and a least-squares
    fit (``ransac.fit_rigid_2d``), stopping when fewer than 3 associate.

    Returns:
        (H, 3) float64 refined poses, (H, N) bool masks of the last association, and (H,) bool ``unsure``:
        hypotheses where a look-up hit a (near-)tie, a distance at a radius or a non-finite point - their pose
        and mask are undefined: refine those with the KD-tree (``alignment.refine_pose``).
    """
    b = buckets
    return _refine_kernel(np.ascontiguousarray(src, dtype=np.float64), np.ascontiguousarray(poses, np.float64),
                          np.asarray(thresholds, np.float64), np.ascontiguousarray(points, np.float64),
                          b.origin_x, b.origin_y, b.inv_cell, b.extent_m, b.nx, b.ny, b.starts, b.order, b.xs,
                          b.ys, TIE_BAND_M2)


def nearest_within(xy: np.ndarray, bound_m: float, buckets: LandmarkBuckets,
                   num_landmarks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest landmark of each point strictly within ``bound_m`` (finite, > 0), as
    ``cKDTree(points).query(xy, distance_upper_bound=bound_m)`` answers, except where flagged.

    Args:
        xy: (K, 2) float64 points, metres (any position, inside the bucket grid or not).
        bound_m: search radius, metres.
        buckets: ``bucket_landmarks(points, ...)`` of the M landmarks.
        num_landmarks: M (the index reported for "none").

    Returns:
        dist: (K,) float64, metres; ``inf`` where no landmark is within the bound.
        idx: (K,) int64 landmark index; M where none.
        unsure: (K,) bool: a (near-)tie, a candidate (nearly) at the bound, or a non-finite point - the tree's
            answer for these points is not reproduced (their dist / idx entries say "none"); ask the tree.
    """
    b = buckets
    return _nearest_within_kernel(np.ascontiguousarray(xy, dtype=np.float64), float(bound_m), b.origin_x,
                                  b.origin_y, b.inv_cell, b.extent_m, b.nx, b.ny, b.starts, b.order, b.xs,
                                  b.ys, int(num_landmarks), TIE_BAND_M2)
