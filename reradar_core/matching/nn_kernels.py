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

__all__ = ["TIE_BAND_M2", "LandmarkBuckets", "bucket_landmarks", "nearest_within"]

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
def _nearest_within_kernel(xy: np.ndarray, bound_m: float, origin_x: float, origin_y: float, inv_cell: float,
                           extent_m: float, nx: int, ny: int, starts: np.ndarray, order: np.ndarray,
                           xs: np.ndarray, ys: np.ndarray, num_landmarks: int,
                           tie_m2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Loop of ``nearest_within`` (arguments: the buckets' fields, unpacked for numba)."""
    k = xy.shape[0]
    dist = np.full(k, np.inf)
    idx = np.full(k, num_landmarks, dtype=np.int64)
    unsure = np.zeros(k, dtype=np.bool_)
    ub = bound_m * bound_m  # scipy squares the bound the same way and compares squared distances to it
    # only a point within the bound of a landmark (|x| <= extent + bound) can find one, and for those the
    # rounding of the square's corners is far below this slack; farther points find none either way
    reach = bound_m + _REACH_SLACK * (1.0 + extent_m + 2.0 * bound_m)
    for p in range(k):
        x = xy[p, 0]
        y = xy[p, 1]
        if not (math.isfinite(x) and math.isfinite(y)):
            unsure[p] = True  # the tree raises on these: let it
            continue
        # search square in cell units, kept as floats (np.floor) and compared before any integer cast, so a
        # point far away cannot overflow the cast
        fx0 = np.floor((x - reach - origin_x) * inv_cell)
        fx1 = np.floor((x + reach - origin_x) * inv_cell)
        fy0 = np.floor((y - reach - origin_y) * inv_cell)
        fy1 = np.floor((y + reach - origin_y) * inv_cell)
        if fx1 < 0 or fy1 < 0 or fx0 > nx - 1 or fy0 > ny - 1:
            continue  # square outside the bucket grid: no landmark within the bound
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
        if edge or (best < ub and second - best <= tie_m2):
            unsure[p] = True
        elif best < ub:
            dist[p] = math.sqrt(best)
            idx[p] = order[best_at]
    return dist, idx, unsure


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
