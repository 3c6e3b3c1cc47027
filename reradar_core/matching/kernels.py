"""Compiled loops of the landmark-alignment counts (``reradar_core.jit``): the same numbers as the numpy path.

Both the candidate screen (``localization.screening``) and the guided pose estimate (``matching.alignment``)
score hypotheses (x, y, yaw) by counting the scored query landmarks that land on a cell of a keyframe's
alignment mask (1 where a keyframe landmark is within the score threshold). numpy does this as ~15 passes
over (P, V) temporaries; here it is one loop per hypothesis with the same floating-point operations in the
same order (IEEE, no fused multiply-add, no re-association), so every cell - and every count - is the same.

Cell of a point: ``floor((x - origin) * inv)`` when the cell size is a power of two (``inverse``: ``inv`` is
1 / cell, an exact scaling) else ``floor((x - origin) / cell)``; a point is on the grid when that floor lies
in [0, n) (numpy's int64 cast of anything else, NaN included, falls outside too).
"""

from __future__ import annotations

import math

import numpy as np

from reradar_core.jit import jit_enabled, njit

__all__ = ["best_aligned_screen", "consistent_pairs_screen", "count_aligned_pose", "count_aligned_screen", "warm_up"]


def count_aligned_pose(sx: np.ndarray, sy: np.ndarray, c: np.ndarray, s: np.ndarray, tx: np.ndarray,
                       ty: np.ndarray, origin: float, cell: float, inverse: bool, n: int,
                       mask: np.ndarray) -> np.ndarray:
    """(V,) int64: for each hypothesis v (cos ``c[v]``, sin ``s[v]``, translation ``tx[v], ty[v]`` metres),
    how many of the (P,) float64 points (``sx``, ``sy``, metres) land on a 1 of the (n * n + 1,) uint8 row-major
    ``mask`` (last entry: outside): ``alignment._score`` + ``LandmarkGrid._count_within_columns``, whose
    x = c sx - s sy + tx is the screen's sx c - sy s + tx (a product does not depend on its operands' order),
    so one keyframe's ``count_aligned_screen``."""
    return count_aligned_screen(sx, sy, c, s, tx, ty, np.zeros(len(c), np.int64), np.array([float(origin)]),
                                np.array([float(cell)]), inverse, np.array([n], np.int64), np.zeros(1, np.int64),
                                mask)


@njit
def _mask_cell(x: float, y: float, c: float, s: float, tx: float, ty: float, origin: float, cell: float,
               inverse: bool, n: int) -> int:  # pragma: no cover - compiled
    """Row-major index ``j * n + i`` of the mask cell where the hypothesis (cos ``c``, sin ``s``, translation
    ``tx, ty``) puts the point (x, y), or -1 off the n x n grid. Arithmetic of ``screening._cells``:
    x' = x c - y s + tx, y' = x s + y c + ty, then floor((x' - origin) * cell) (``inverse``) or / cell."""
    fi = x * c - y * s + tx - origin
    fj = x * s + y * c + ty - origin
    if inverse:
        fi *= cell
        fj *= cell
    else:
        fi /= cell
        fj /= cell
    fi = math.floor(fi)
    fj = math.floor(fj)
    nf = float(n)
    if fi >= 0.0 and fi < nf and fj >= 0.0 and fj < nf:
        return int(fj) * n + int(fi)
    return -1


@njit
def count_aligned_screen(sx: np.ndarray, sy: np.ndarray, c: np.ndarray, s: np.ndarray, tx: np.ndarray,
                         ty: np.ndarray, cand: np.ndarray, origins: np.ndarray, cells: np.ndarray,
                         inverse: bool, sizes: np.ndarray, offsets: np.ndarray,
                         near: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """(V,) int64 aligned counts of V hypotheses over several keyframes (``screening._aligned_counts``):
    hypothesis v belongs to candidate ``cand[v]``, whose mask starts at ``offsets[cand[v]]`` in ``near`` (all
    masks concatenated) with ``sizes`` cells per side, lower corner ``origins`` and cell (or inverse cell)
    ``cells``. Arithmetic of ``screening._cells``: x = sx c - sy s + tx, y = sx s + sy c + ty."""
    num_v = c.shape[0]
    num_p = sx.shape[0]
    out = np.zeros(num_v, np.int64)
    for v in range(num_v):
        cv, sv, tv, uv = c[v], s[v], tx[v], ty[v]
        g = cand[v]
        go, gc, n, off = origins[g], cells[g], sizes[g], offsets[g]
        k = 0
        for p in range(num_p):
            cell = _mask_cell(sx[p], sy[p], cv, sv, tv, uv, go, gc, inverse, n)
            if cell >= 0:
                k += near[off + cell]
        out[v] = k
    return out


@njit
def best_aligned_screen(sx: np.ndarray, sy: np.ndarray, c: np.ndarray, s: np.ndarray, tx: np.ndarray,
                        ty: np.ndarray, cand: np.ndarray, origins: np.ndarray, cells: np.ndarray,
                        inverse: bool, sizes: np.ndarray, bit_offsets: np.ndarray, packed: np.ndarray,
                        num_candidates: int) -> np.ndarray:  # pragma: no cover - compiled
    """(K,) int64: each candidate's largest ``count_aligned_screen`` count over its hypotheses (0 without any),
    read from the bit-packed masks (``packed``: every ``ScreenGrid.packed`` concatenated, candidate g's mask
    starting at bit ``bit_offsets[g]``, ``np.packbits``' big-endian bit order), so the masks are never unpacked.

    A hypothesis stops counting once the points left cannot lift it above its candidate's best so far: the
    maximum is the same number, and the poorly aligned hypotheses of a candidate with one good pose skip their
    last points (~45 % less time than the full counts on the screen's real calls, with the packed masks).
    """
    num_v = c.shape[0]
    num_p = sx.shape[0]
    best = np.zeros(num_candidates, np.int64)
    for v in range(num_v):
        cv, sv, tv, uv = c[v], s[v], tx[v], ty[v]
        g = cand[v]
        go, gc, n, off = origins[g], cells[g], sizes[g], bit_offsets[g]
        bar = best[g]
        k = 0
        for p in range(num_p):
            if k + num_p - p <= bar:  # even every remaining point aligned would not beat the best
                break
            cell = _mask_cell(sx[p], sy[p], cv, sv, tv, uv, go, gc, inverse, n)
            if cell >= 0:
                bit = off + cell
                k += (packed[bit >> 3] >> (7 - (bit & 7))) & 1
        if k > bar:
            best[g] = k
    return best


#: ``consistent_pairs_screen``'s verdicts
PAIR_REJECTED, PAIR_CONSISTENT, PAIR_BORDERLINE = 0, 1, 2


@njit
def consistent_pairs_screen(land: np.ndarray, a: np.ndarray, b: np.ndarray, fx: np.ndarray, fy: np.ndarray,
                            ls: np.ndarray, source_ok: np.ndarray, max_mismatch_m: float,
                            verdict: np.ndarray) -> None:  # pragma: no cover - compiled
    """The screen's length-consistency test of every candidate's minimal sets, without the (K, H) temporaries.

    Minimal set h of candidate g pairs keyframe landmarks ``land[g, a[h]]`` and ``land[g, b[h]]`` (flat
    indices into ``fx`` / ``fy``, metres) with two query landmarks ``ls[h]`` metres apart; the numpy path keeps
    it when ``source_ok[h]`` and ``abs(ls[h] - hypot(dx, dy)) < max_mismatch_m``. Here the length is compared
    squared, with a margin (1e-9 of the lengths, far above the rounding of either form) that makes every
    verdict outside it the numpy path's; the few minimal sets within it are marked ``PAIR_BORDERLINE`` in
    ``verdict`` (K, H) int8 for the caller to decide with the numpy expression itself.
    """
    num_k, num_h = verdict.shape
    for g in range(num_k):
        for h in range(num_h):
            if not source_ok[h]:
                verdict[g, h] = PAIR_REJECTED
                continue
            i, j = land[g, a[h]], land[g, b[h]]
            dx = fx[j] - fx[i]
            dy = fy[j] - fy[i]
            d2 = dx * dx + dy * dy
            lo = ls[h] - max_mismatch_m
            hi = ls[h] + max_mismatch_m
            eps = 1e-9 * (hi + 1.0)
            if d2 >= (hi + eps) * (hi + eps) or (lo - eps > 0.0 and d2 <= (lo - eps) * (lo - eps)):
                verdict[g, h] = PAIR_REJECTED
            elif d2 < (hi - eps) * (hi - eps) and (lo + eps <= 0.0 or d2 > (lo + eps) * (lo + eps)):
                verdict[g, h] = PAIR_CONSISTENT
            else:
                verdict[g, h] = PAIR_BORDERLINE


def warm_up() -> bool:
    """Compile (or load from the disk cache) every kernel of the query path now, with tiny inputs, so that no
    request pays for it; returns whether the kernels run (``jit_enabled``)."""
    if not jit_enabled():
        return False
    one = np.zeros(1)
    mask = np.zeros(5, np.uint8)
    count_aligned_screen(one, one, one, one, one, one, np.zeros(1, np.int64), one, np.full(1, 2.0), True,
                         np.full(1, 2, np.int64), np.zeros(1, np.int64), mask)
    best_aligned_screen(one, one, one, one, one, one, np.zeros(1, np.int64), one, np.full(1, 2.0), True,
                        np.full(1, 2, np.int64), np.zeros(1, np.int64), mask, 1)
    consistent_pairs_screen(np.zeros((1, 1), np.int64), np.zeros(1, np.int64), np.zeros(1, np.int64), one, one,
                            one, np.ones(1, bool), 3.0, np.zeros((1, 1), np.int8))
    from reradar_core.matching.nn_kernels import bucket_landmarks, nearest_within, refine_poses

    pts = np.array([[0.0, 0.0], [3.0, 1.0]])
    buckets = bucket_landmarks(pts, 2.0, 64)
    nearest_within(pts, 2.0, buckets, len(pts))
    refine_poses(pts, np.zeros((1, 3)), (2.0, 1.0), pts, buckets)
    from reradar_core.matching.motion_kernels import motion_fit

    motion_fit(pts, np.zeros(2), pts, buckets, np.zeros(6), np.zeros(6), np.ones(6), (2.0,), 1, 1)
    from reradar_core.landmarks.cen2018_kernels import warm_up as warm_up_detector

    warm_up_detector()  # the landmark detector of every query's features
    return True
