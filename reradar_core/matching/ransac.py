"""RANSAC estimation of a 2-D rigid transform (rotation + translation, no scale) from point matches.

Used to verify a retrieved keyframe and estimate the 3-DoF pose (paper, Sec. Pose Estimation): the source
points are the query scan's matched landmarks, the destination points the keyframe's, both in metres in
their sensor frames, so the result is ``T_keyframe_query`` (docs/CONVENTIONS.md).

Minimal solver: two correspondences. The rotation is the angle between the two difference vectors
(any heading in [0, 2 pi)), the translation follows from the pair's midpoints. Hypotheses are scored in
chunks with broadcasting; the iteration count adapts to the best inlier ratio (Fischler & Bolles 1981),
capped by ``max_iterations``. The winner is refit by least squares on its inliers (2-D Kabsch / Umeyama
without scale) and its inliers re-evaluated until the set is stable.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from reradar_core.errors import ConfigError

__all__ = ["RansacConfig", "RigidEstimate", "estimate_rigid_2d", "fit_rigid_2d"]

logger = logging.getLogger(__name__)

#: Hypotheses scored per broadcast chunk: (chunk, N, 2) residuals, ~1.5 MB for N = 1,000.
_CHUNK = 64
#: Refit/re-evaluate rounds after RANSAC (stops earlier when the inlier set no longer changes).
_REFIT_ROUNDS = 5
#: Minimal sets whose points are closer than this (metres) define no rotation.
_MIN_BASELINE_M = 1e-6


@dataclass(frozen=True)
class RansacConfig:
    """RANSAC parameters.

    Attributes:
        inlier_threshold_m: a match is an inlier if ||dst - (R src + t)|| <= this, metres. Default 1.0 m,
            about 1.5 pixels of the 0.64 m/px Cartesian image the local descriptors are read from, so a
            landmark whose descriptor lands in the neighbouring pixel still counts.
        max_iterations: cap on the number of minimal-set hypotheses (default 1,000).
        confidence: probability of drawing at least one all-inlier minimal set, sets the adaptive iteration
            count (default 0.999).
        min_matches: below this many (finite) matches no pose is estimated (default 3).
        min_inliers: a pose is accepted only with at least this many inliers (default 6).
        seed: seed of the numpy Generator that draws the minimal sets (deterministic results).
    """

    inlier_threshold_m: float = 1.0
    max_iterations: int = 1000
    confidence: float = 0.999
    min_matches: int = 3
    min_inliers: int = 6
    seed: int = 0

    def __post_init__(self) -> None:
        if not (self.inlier_threshold_m > 0 and math.isfinite(self.inlier_threshold_m)):
            raise ConfigError(f"inlier_threshold_m must be positive, got {self.inlier_threshold_m}")
        if self.max_iterations < 1:
            raise ConfigError(f"max_iterations must be >= 1, got {self.max_iterations}")
        if not (0.0 < self.confidence < 1.0):
            raise ConfigError(f"confidence must be in (0, 1), got {self.confidence}")
        if self.min_matches < 2:
            raise ConfigError(f"min_matches must be >= 2 (the minimal set), got {self.min_matches}")
        if self.min_inliers < 2:
            raise ConfigError(f"min_inliers must be >= 2, got {self.min_inliers}")


@dataclass
class RigidEstimate:
    """Result of ``estimate_rigid_2d``.

    Attributes:
        success: True if a pose with at least ``min_inliers`` inliers was found.
        pose: (3,) float64 T_dst_src = (x [m], y [m], yaw [rad] in (-pi, pi]): dst ~= R(yaw) src + (x, y).
            The best pose found even when ``success`` is False (too few inliers); NaN if none was found.
        num_inliers: inliers of ``pose``.
        inlier_ratio: num_inliers / number of input matches (0 for no matches).
        inlier_mask: (N,) bool over the input matches.
        reason: why ``success`` is False (None on success).
        num_iterations: minimal-set hypotheses drawn.
        rmse_m: root-mean-square inlier residual, metres (NaN without inliers).
        ambiguity: guided estimator only: the best rival pose's alignment score / the answer's (0 = unique,
            1 = tie; NaN where not computed).
    """

    success: bool
    pose: np.ndarray
    num_inliers: int
    inlier_ratio: float
    inlier_mask: np.ndarray
    reason: str | None = None
    num_iterations: int = 0
    rmse_m: float = float("nan")
    ambiguity: float = float("nan")


def _failure(n: int, reason: str, pose: np.ndarray | None = None, mask: np.ndarray | None = None,
             iterations: int = 0) -> RigidEstimate:
    mask = np.zeros(n, dtype=bool) if mask is None else mask
    k = int(mask.sum())
    return RigidEstimate(
        success=False,
        pose=np.full(3, np.nan) if pose is None else pose,
        num_inliers=k,
        inlier_ratio=k / n if n else 0.0,
        inlier_mask=mask,
        reason=reason,
        num_iterations=iterations,
    )


def fit_rigid_2d(points_src: np.ndarray, points_dst: np.ndarray,
                 weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares rigid transform (2-D Kabsch / Umeyama, no scale) with dst ~= R src + t.

    Args:
        points_src: (N, 2) float metres, N >= 2 and not all coincident.
        points_dst: (N, 2) float metres.
        weights: optional (N,) non-negative weights.

    Returns:
        (3,) float64 T_dst_src = (x, y, yaw).

    Raises:
        ValueError: the points are not both (N, 2) with N >= 2, or the weights not (N,) non-negative.

    Unweighted, every sum is taken left to right (``_sequential_sum``): the compiled refinement
    (``matching.nn_kernels.refine_poses``) does the same operations in the same order, so both give the same
    numbers - a BLAS product's summation order is the library's and the machine's, a loop's is not.
    """
    src = np.asarray(points_src, dtype=np.float64)
    dst = np.asarray(points_dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 2 or dst.shape != src.shape:  # a (2, N) pair fits a wrong pose silently
        raise ValueError(f"points_src and points_dst must both be (N, 2), got {src.shape} and {dst.shape}")
    n = len(src)
    if n < 2:
        raise ValueError(f"a rigid fit needs N >= 2 point pairs, got {n}")
    if weights is None:
        # centroids, then yaw = atan2(sum (a x b), sum (a . b)) over the centred points a, b
        ms0, ms1 = _sequential_sum(src[:, 0]) / n, _sequential_sum(src[:, 1]) / n
        md0, md1 = _sequential_sum(dst[:, 0]) / n, _sequential_sum(dst[:, 1]) / n
        a0, a1 = src[:, 0] - ms0, src[:, 1] - ms1
        b0, b1 = dst[:, 0] - md0, dst[:, 1] - md1
        yaw = math.atan2(_sequential_sum(a0 * b1 - a1 * b0), _sequential_sum(a0 * b0 + a1 * b1))
        c, s = math.cos(yaw), math.sin(yaw)
        return np.array([md0 - (c * ms0 - s * ms1), md1 - (s * ms0 + c * ms1), yaw])
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (n,) or not (np.all(w >= 0) and w.sum() > 0):
        raise ValueError(f"weights must be ({n},) non-negative with a positive sum, got shape {w.shape}")
    w = w / w.sum()
    mu_s = w @ src
    mu_d = w @ dst
    a = src - mu_s
    b = dst - mu_d
    # In 2-D the optimal rotation angle is atan2(sum w (a x b), sum w (a . b))
    ab = a * b  # a0 b0, a1 b1
    abr = a * b[:, ::-1]  # a0 b1, a1 b0
    yaw = math.atan2(float(np.sum(w * (abr[:, 0] - abr[:, 1]))), float(np.sum(w * (ab[:, 0] + ab[:, 1]))))
    c, s = math.cos(yaw), math.sin(yaw)
    ms0, ms1 = float(mu_s[0]), float(mu_s[1])
    return np.array([float(mu_d[0]) - (c * ms0 - s * ms1), float(mu_d[1]) - (s * ms0 + c * ms1), yaw])


def _sequential_sum(x: np.ndarray) -> float:
    """x[0] + x[1] + ... added left to right (``np.cumsum`` is a running sum; ``np.sum`` adds pairwise)."""
    return float(np.cumsum(x)[-1]) if len(x) else 0.0


def _residuals_sq(pose: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    dx = c * src[:, 0] - s * src[:, 1] + pose[0] - dst[:, 0]
    dy = s * src[:, 0] + c * src[:, 1] + pose[1] - dst[:, 1]
    return dx * dx + dy * dy


def _required_iterations(inlier_ratio: float, confidence: float, cap: int) -> int:
    """Hypotheses needed to draw one all-inlier pair with probability ``confidence``."""
    p_good = inlier_ratio * inlier_ratio
    if p_good >= 1.0:
        return 1
    if p_good <= 0.0:
        return cap
    return int(min(cap, math.ceil(math.log(1.0 - confidence) / math.log(1.0 - p_good))))


def estimate_rigid_2d(points_src: np.ndarray, points_dst: np.ndarray,
                      config: RansacConfig | None = None) -> RigidEstimate:
    """Robustly estimate T_dst_src from putative matches ``points_src[i] <-> points_dst[i]``.

    Args:
        points_src: (N, 2) float source points, metres (e.g. query landmarks, query sensor frame).
        points_dst: (N, 2) float destination points, metres (e.g. keyframe landmarks, keyframe frame).
        config: RANSAC parameters (defaults: ``RansacConfig()``).

    Returns:
        ``RigidEstimate``; problems with the data (too few matches, non-finite values, degenerate geometry,
        too few inliers) give ``success=False`` and a ``reason``, never an exception.

    Raises:
        ValueError: the arrays are not (N, 2) with the same N (a programming error, not a data problem).
    """
    config = config or RansacConfig()
    src = np.asarray(points_src, dtype=np.float64)
    dst = np.asarray(points_dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[-1] != 2 or dst.shape != src.shape:
        raise ValueError(f"points_src and points_dst must both be (N, 2), got {src.shape} and {dst.shape}")
    n = src.shape[0]
    if n < config.min_matches:
        return _failure(n, f"too few matches: {n} < min_matches={config.min_matches}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        return _failure(n, "non-finite (NaN or infinite) point coordinates")
    if np.ptp(src, axis=0).max() < _MIN_BASELINE_M or np.ptp(dst, axis=0).max() < _MIN_BASELINE_M:
        return _failure(n, "degenerate: all source or all destination points coincide")

    rng = np.random.default_rng(config.seed)
    thr_sq = config.inlier_threshold_m ** 2
    # A rigid transform preserves distances: a pair whose source and destination baselines differ by more
    # than twice the threshold cannot be two inliers, so it is not scored (it still counts as drawn).
    max_len_diff = 2.0 * config.inlier_threshold_m

    best_count = -1
    best_cost = np.inf
    best_pose: np.ndarray | None = None
    required = config.max_iterations
    drawn = 0
    while drawn < min(required, config.max_iterations):
        k = min(_CHUNK, config.max_iterations - drawn)
        i = rng.integers(0, n, size=k)
        j = (i + rng.integers(1, n, size=k)) % n  # j != i
        drawn += k
        vs = src[j] - src[i]
        vd = dst[j] - dst[i]
        ls = np.hypot(vs[:, 0], vs[:, 1])
        ld = np.hypot(vd[:, 0], vd[:, 1])
        ok = (ls > _MIN_BASELINE_M) & (ld > _MIN_BASELINE_M) & (np.abs(ls - ld) <= max_len_diff)
        if not np.any(ok):
            continue
        i, j, vs, vd = i[ok], j[ok], vs[ok], vd[ok]
        yaw = np.arctan2(vs[:, 0] * vd[:, 1] - vs[:, 1] * vd[:, 0], vs[:, 0] * vd[:, 0] + vs[:, 1] * vd[:, 1])
        c, s = np.cos(yaw), np.sin(yaw)
        ms = 0.5 * (src[i] + src[j])
        md = 0.5 * (dst[i] + dst[j])
        tx = md[:, 0] - (c * ms[:, 0] - s * ms[:, 1])
        ty = md[:, 1] - (s * ms[:, 0] + c * ms[:, 1])
        # (H, N) squared residuals of every hypothesis on every match.
        dx = c[:, None] * src[None, :, 0] - s[:, None] * src[None, :, 1] + tx[:, None] - dst[None, :, 0]
        dy = s[:, None] * src[None, :, 0] + c[:, None] * src[None, :, 1] + ty[:, None] - dst[None, :, 1]
        r2 = dx * dx + dy * dy
        inl = r2 <= thr_sq
        counts = inl.sum(axis=1)
        # Ties on the inlier count are broken by the MSAC cost (truncated squared residuals).
        cost = np.minimum(r2, thr_sq).sum(axis=1)
        h = int(np.lexsort((cost, -counts))[0])
        if counts[h] > best_count or (counts[h] == best_count and cost[h] < best_cost):
            best_count, best_cost = int(counts[h]), float(cost[h])
            best_pose = np.array([tx[h], ty[h], yaw[h]])
            required = _required_iterations(best_count / n, config.confidence, config.max_iterations)

    if best_pose is None:
        return _failure(n, "degenerate: no usable minimal set (coincident points or inconsistent distances)",
                        iterations=drawn)

    pose = best_pose
    mask = _residuals_sq(pose, src, dst) <= thr_sq
    for _ in range(_REFIT_ROUNDS):
        if mask.sum() < 2:
            break
        if np.ptp(src[mask], axis=0).max() < _MIN_BASELINE_M:
            break  # all inliers at one point: the refit would have no rotation
        # The least-squares fit on the consensus set is more precise than the two-point hypothesis.
        pose = fit_rigid_2d(src[mask], dst[mask])
        new_mask = _residuals_sq(pose, src, dst) <= thr_sq
        changed = bool(np.any(new_mask != mask))
        mask = new_mask
        if not changed:
            break

    pose = np.array([pose[0], pose[1], math.remainder(pose[2], 2.0 * math.pi)])
    if pose[2] == -math.pi:
        pose[2] = math.pi
    num_inliers = int(mask.sum())
    r2 = _residuals_sq(pose, src, dst)
    rmse = float(np.sqrt(r2[mask].mean())) if num_inliers else float("nan")
    if num_inliers < config.min_inliers:
        est = _failure(n, f"too few inliers: {num_inliers} < min_inliers={config.min_inliers}", pose, mask, drawn)
        est.rmse_m = rmse
        return est
    return RigidEstimate(
        success=True,
        pose=pose,
        num_inliers=num_inliers,
        inlier_ratio=num_inliers / n,
        inlier_mask=mask,
        reason=None,
        num_iterations=drawn,
        rmse_m=rmse,
    )
