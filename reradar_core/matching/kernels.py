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

__all__ = ["count_aligned_pose", "count_aligned_screen", "warm_up"]


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
        nf = float(n)
        k = 0
        for p in range(num_p):
            fi = sx[p] * cv - sy[p] * sv + tv - go
            fj = sx[p] * sv + sy[p] * cv + uv - go
            if inverse:
                fi *= gc
                fj *= gc
            else:
                fi /= gc
                fj /= gc
            fi = math.floor(fi)
            fj = math.floor(fj)
            if fi >= 0.0 and fi < nf and fj >= 0.0 and fj < nf:
                k += near[off + int(fj) * n + int(fi)]
        out[v] = k
    return out


def warm_up() -> bool:
    """Compile (or load from the disk cache) every kernel of the query path now, with tiny inputs, so that no
    request pays for it; returns whether the kernels run (``jit_enabled``)."""
    if not jit_enabled():
        return False
    one = np.zeros(1)
    mask = np.zeros(5, np.uint8)
    count_aligned_screen(one, one, one, one, one, one, np.zeros(1, np.int64), one, np.full(1, 2.0), True,
                         np.full(1, 2, np.int64), np.zeros(1, np.int64), mask)
    from reradar_core.matching.nn_kernels import bucket_landmarks, nearest_within, refine_poses

    pts = np.array([[0.0, 0.0], [3.0, 1.0]])
    buckets = bucket_landmarks(pts, 2.0, 64)
    nearest_within(pts, 2.0, buckets, len(pts))
    refine_poses(pts, np.zeros((1, 3)), (2.0, 1.0), pts, buckets)
    return True
