"""Compiled loop of ``matching.motion.motion_polish`` (numba; the numpy path runs without it).

The fit's ~20 numpy passes over a few hundred landmarks per Gauss-Newton step, 12 steps an answer, cost ~4 ms in
Python call overhead alone; one compiled loop over the landmarks per step (association through the landmark buckets
of ``nn_kernels``, the normal equations accumulated in place) costs a fraction of it. It does the same operations
as the numpy path except the order of the normal equations' sums (BLAS there, left to right here), so the two agree
to rounding (1e-9 m tested), not to the bit (``tests/matching/test_matching_motion.py`` compares them); a look-up that
hits a near-tie (``TIE_BAND_M2``) makes the caller take the numpy path, whose KD-tree decides it.
"""

from __future__ import annotations

import math

import numpy as np

from reradar_core.jit import njit
from reradar_core.matching.nn_kernels import TIE_BAND_M2, LandmarkBuckets, _nearest_point, _reach

__all__ = ["motion_fit"]


@njit
def _motion_fit_kernel(src: np.ndarray, tau: np.ndarray, dst: np.ndarray, x0: np.ndarray, prior_mean: np.ndarray,
                       prior_precision: np.ndarray, radii: np.ndarray, iterations: int, min_associated: int,
                       origin_x: float, origin_y: float, inv_cell: float, extent_m: float, nx: int, ny: int,
                       starts: np.ndarray, order: np.ndarray, xs: np.ndarray, ys: np.ndarray,
                       tie_m2: float) -> tuple[np.ndarray, int, bool]:  # pragma: no cover - compiled
    x = x0.copy()
    n = src.shape[0]
    associated = 0
    jx = np.zeros(6)
    jy = np.zeros(6)
    for r in range(radii.shape[0]):
        bound = radii[r]
        ub = bound * bound
        reach = _reach(bound, extent_m)
        for _ in range(iterations):
            c, s = math.cos(x[2]), math.sin(x[2])
            hessian = np.zeros((6, 6))
            gradient = np.zeros(6)
            k = 0
            for p in range(n):
                t = tau[p]
                cw, sw = math.cos(x[5] * t), math.sin(x[5] * t)
                lx = cw * src[p, 0] - sw * src[p, 1] + x[3] * t  # ``deskew_points``
                ly = sw * src[p, 0] + cw * src[p, 1] + x[4] * t
                px = c * lx - s * ly + x[0]
                py = s * lx + c * ly + x[1]
                best, best_at, flag = _nearest_point(px, py, ub, reach, origin_x, origin_y, inv_cell, nx, ny,
                                                     starts, xs, ys, tie_m2)
                if flag:
                    return x, -1, True
                if best < ub:
                    q = order[best_at]
                    rx, ry = dst[q, 0] - px, dst[q, 1] - py
                    ax = -(sw * src[p, 0] + cw * src[p, 1]) * t  # d(R(w tau) p)/dw = tau R'(w tau) p
                    ay = (cw * src[p, 0] - sw * src[p, 1]) * t
                    # the two Jacobian rows: x (1, 0, a2, a3, a4, a5) and y (0, 1, b2, b3, b4, b5)
                    jx[2], jx[3], jx[4], jx[5] = -s * lx - c * ly, c * t, -s * t, c * ax - s * ay
                    jy[2], jy[3], jy[4], jy[5] = c * lx - s * ly, s * t, c * t, s * ax + c * ay
                    gradient[0] += rx
                    gradient[1] += ry
                    for i in range(2, 6):
                        gradient[i] += jx[i] * rx + jy[i] * ry
                        hessian[0, i] += jx[i]
                        hessian[1, i] += jy[i]
                        for j in range(i, 6):
                            hessian[i, j] += jx[i] * jx[j] + jy[i] * jy[j]
                    k += 1
            associated = k
            if k < min_associated:
                return x, k, False
            hessian[0, 0] = k
            hessian[1, 1] = k
            for i in range(6):  # the upper triangle was accumulated
                for j in range(i):
                    hessian[i, j] = hessian[j, i]
            for i in range(6):
                hessian[i, i] += prior_precision[i] + 1e-9
                gradient[i] -= prior_precision[i] * (x[i] - prior_mean[i])
            x = x + np.linalg.solve(hessian, gradient)
    return x, associated, False


def motion_fit(src: np.ndarray, tau: np.ndarray, dst: np.ndarray, buckets: LandmarkBuckets, x0: np.ndarray,
               prior_mean: np.ndarray, prior_precision: np.ndarray, radii: tuple[float, ...],
               iterations: int, min_associated: int) -> tuple[np.ndarray, int, bool]:
    """The Gauss-Newton rounds of ``motion_polish`` compiled: (6,) parameters (pose, motion), landmarks associated
    at the last step (fewer than ``min_associated``: the fit stopped there), and ``unsure`` (a near-tie look-up:
    redo the fit with the numpy path)."""
    b = buckets
    return _motion_fit_kernel(np.ascontiguousarray(src, np.float64), np.ascontiguousarray(tau, np.float64),
                              np.ascontiguousarray(dst, np.float64), np.asarray(x0, np.float64),
                              np.asarray(prior_mean, np.float64), np.asarray(prior_precision, np.float64),
                              np.asarray(radii, np.float64), int(iterations), int(min_associated), b.origin_x,
                              b.origin_y, b.inv_cell, b.extent_m, b.nx, b.ny, b.starts, b.order, b.xs, b.ys,
                              TIE_BAND_M2)
