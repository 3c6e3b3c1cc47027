"""How precise an answer's pose is: the covariance of a landmark registration, calibrated on training data.

A vehicle fusing ReRadar's answers with its own odometry (a Kalman filter, a pose graph) needs each answer's
uncertainty, not only whether it is right (``confidence``): along a street lined by one façade the pose is pinned
across the street and loose along it; with landmarks on every side it is pinned both ways. The registration's
own geometry says which, to first order: with the final pose's landmark pairs (query landmark p_i in its sensor
frame, keyframe landmark q_i in the keyframe's frame, both de-skewed when the pose is motion-compensated) and the
residual r_i = q_i - (R(yaw) p_i + t), the Gauss-Newton normal matrix of (x, y, yaw) is

    H = sum_i J_i^T W_i J_i,   J_i = [I_2 | perp(R p_i)],   perp(v) = (-v_y, v_x),

and the least-squares covariance sigma^2 H^-1 with sigma^2 = sum r_i^T W_i r_i / (sum tr W_i - 3), plus a weak prior
(``prior_sigma_m`` / ``prior_sigma_deg``). W_i says what a pair pins: a keyframe landmark alone (a pole) pins both
directions (W = I); one on a wall, whose neighbours within
``neighbourhood_m`` lie along a line, pins only the direction across it, because a pose slid along the wall pairs
every landmark with another point of the same wall just as closely (W = n n^T + (l1 / l2) t t^T, with n, t the
normal and the tangent, l1 <= l2 the eigenvalues of the neighbours' scatter: I for a round cluster, n n^T for a
straight line; point-to-line ICP, Censi 2007). So a street lined by façades on one side only comes out loose along
the street. That figure assumes independent landmark errors; two scans' landmarks are not (the same structure,
detected with the same biases, the sweep's motion fitted from them), so it is 3-8 times too small in standard
deviation. ``position_scale`` and ``heading_scale`` inflate the position block and the heading variance (S C S with
S = diag(sqrt(k_t), sqrt(k_t), sqrt(k_r)): correlations unchanged), one pair for a motion-compensated pose and one for
a rigid registration's (``rigid_*``), each chosen so that 95 % of the training splits' right answers of that kind lie
inside the 95 % ellipse / interval (``benchmarks/pose_covariance.py``, docs/MODEL.md "Pose covariance"), never on a
benchmark query sequence.

Frames and units: the covariance is of ``T_dst_src`` (x m, y m, yaw rad) in the destination (keyframe) frame;
``rotate_covariance`` expresses it in another frame (the map's: ``T_map_keyframe``'s heading). The keyframe's own
map pose is taken as exact: a map's pose errors add to it (they are the map builder's, docs/MAP_FORMAT.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from reradar_core.errors import ConfigError
from reradar_core.geometry.se2 import transform_points

__all__ = ["PoseCovarianceConfig", "landmark_information", "registration_covariance", "rotate_covariance"]


@dataclass(frozen=True)
class PoseCovarianceConfig:
    """Settings of an answer's pose covariance (``registration_covariance``).

    Attributes:
        enabled: give localized answers a covariance (False: none, ``LocalizationResult.pose_covariance`` None).
        radius_m: a query landmark pairs with the nearest keyframe landmark within this distance at the final pose
            (0.75 m: the pose polish's association radius).
        neighbourhood_m: a keyframe landmark's shape (a point, or a stretch of a line: ``W_i``) is read from its
            nearest ``neighbours`` keyframe landmarks within this distance (1.5 m, 8); fewer than 3: a point.
        min_pairs: fewer pairs than this give no covariance (too few to say; a localized answer has at least 12
            aligned landmarks).
        position_scale: variance factor on the position block of sigma^2 H^-1 for a motion-compensated pose (fitted
            on the training splits, ``benchmarks/pose_covariance.py``: 95 % of their right answers' position errors
            inside the 95 % ellipse).
        heading_scale: variance factor on the heading variance of a motion-compensated pose (fitted likewise).
        rigid_position_scale, rigid_heading_scale: the same for a rigid registration's pose (no compensation: the
            two sweeps' skews are left in it where they do not cancel, which its landmark pairs cannot show).
        prior_sigma_m, prior_sigma_deg: a prior on the pose (10 m, 10 deg: a right answer lies within the success
            thresholds, 20 m / 10 deg), added to the registration's information, so that a direction the landmarks
            do not pin (every landmark on one straight wall) gets this much uncertainty rather than none at all
            (at most 1000 m / 180 deg).
        The rigid scales were fitted on answers whose compensation was discarded or whose keyframe's motion was
        unknown (the shipped settings' rigid answers); with the compensation switched off
        (``MotionConfig(enabled=False)``) every answer takes them, a population not measured separately.
    """

    enabled: bool = True
    radius_m: float = 0.75
    neighbourhood_m: float = 1.5
    neighbours: int = 8
    min_pairs: int = 12
    position_scale: float = 10.6
    heading_scale: float = 42.3
    rigid_position_scale: float = 15.1
    rigid_heading_scale: float = 63.2
    prior_sigma_m: float = 10.0
    prior_sigma_deg: float = 10.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.radius_m) and 0.0 < self.radius_m <= 10.0):
            raise ConfigError(f"pose covariance radius_m must be in (0, 10] m, got {self.radius_m}")
        if not (math.isfinite(self.neighbourhood_m) and 0.0 < self.neighbourhood_m <= 10.0
                and 3 <= self.neighbours <= 64):
            raise ConfigError("pose covariance neighbourhood_m must be in (0, 10] m and neighbours in [3, 64], got "
                              f"{self.neighbourhood_m} and {self.neighbours}")
        if not 3 <= self.min_pairs <= 10_000:
            raise ConfigError(f"pose covariance min_pairs must be in [3, 10000], got {self.min_pairs}")
        for name in ("position_scale", "heading_scale", "rigid_position_scale", "rigid_heading_scale"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 1e-6 <= v <= 1e6):
                raise ConfigError(f"pose covariance {name} must be in [1e-6, 1e6], got {v}")
        # a looser prior leaves a free direction (one straight wall) so weakly pinned that the inverse loses its
        # positive definiteness in float64 (review, session 31: eigenvalues down to -1e27 at 1e6 m)
        if not (math.isfinite(self.prior_sigma_m) and 1e-3 <= self.prior_sigma_m <= 1e3):
            raise ConfigError(f"pose covariance prior_sigma_m must be in [0.001, 1000] m, got {self.prior_sigma_m}")
        if not (math.isfinite(self.prior_sigma_deg) and 1e-3 <= self.prior_sigma_deg <= 180.0):
            raise ConfigError(f"pose covariance prior_sigma_deg must be in [0.001, 180] deg, got {self.prior_sigma_deg}")

    @property
    def prior_information(self) -> np.ndarray:
        """(3, 3) float64 the prior's information (inverse covariance) on (x m, y m, yaw rad): diag(1 / sigma^2)."""
        return np.diag([self.prior_sigma_m ** -2, self.prior_sigma_m ** -2, math.radians(self.prior_sigma_deg) ** -2])


def registration_covariance(src_xy_m: np.ndarray, dst_xy_m: np.ndarray, T_dst_src: np.ndarray,
                            config: PoseCovarianceConfig = PoseCovarianceConfig(),
                            motion_compensated: bool = True) -> np.ndarray | None:
    """Covariance of a registered pose from its landmark pairs (module docstring), calibrated.

    Args:
        src_xy_m: (N, 2) the query's landmarks in its sensor frame, metres (de-skewed when the pose is).
        dst_xy_m: (M, 2) the keyframe's landmarks in its sensor frame, metres (likewise).
        T_dst_src: (3,) the registered pose (x m, y m, yaw rad) of the query in the keyframe's frame.
        config: association radius, minimum pairs and the fitted scales.
        motion_compensated: the pose is a motion-compensated one (``position_scale`` / ``heading_scale``), or a rigid
            registration's (``rigid_position_scale`` / ``rigid_heading_scale``).
    Returns:
        (3, 3) float64 covariance of (x m, y m, yaw rad) in the keyframe's frame (m^2, m rad, rad^2), or None when
        fewer than ``min_pairs`` landmarks pair, an input is not finite, or the result is not a positive definite
        matrix of finite numbers. A direction the pairs do not fix (every landmark on one straight wall leaves the
        pose free along it) gets the prior's uncertainty.
    """
    src = np.asarray(src_xy_m, np.float64).reshape(-1, 2)
    dst = np.asarray(dst_xy_m, np.float64).reshape(-1, 2)
    pose = np.asarray(T_dst_src, np.float64).reshape(3)
    if (len(src) < config.min_pairs or len(dst) < config.min_pairs or not np.isfinite(pose).all()
            or not np.isfinite(src).all() or not np.isfinite(dst).all()):
        return None
    pred = transform_points(pose, src)
    tree = cKDTree(dst)
    dist, idx = tree.query(pred, distance_upper_bound=config.radius_m)
    paired = np.isfinite(dist)
    n = int(paired.sum())
    if n < config.min_pairs:
        return None
    arm = pred[paired] - pose[:2]  # R p_i: the landmark as rotated, from the pose's origin
    residual = dst[idx[paired]] - pred[paired]
    weight = landmark_information(dst, idx[paired], tree, config)  # (n, 2, 2) W_i
    w00, w01, w11 = weight[:, 0, 0], weight[:, 0, 1], weight[:, 1, 1]
    gx, gy = -arm[:, 1], arm[:, 0]  # d(R p_i) / d yaw
    # H = sum J_i^T W_i J_i with J_i = [I | g_i], written out
    h = np.empty((3, 3))
    h[0, 0], h[0, 1], h[1, 1] = w00.sum(), w01.sum(), w11.sum()
    h[0, 2] = (w00 * gx + w01 * gy).sum()
    h[1, 2] = (w01 * gx + w11 * gy).sum()
    h[2, 2] = (w00 * gx * gx + 2.0 * w01 * gx * gy + w11 * gy * gy).sum()
    h[1, 0], h[2, 0], h[2, 1] = h[0, 1], h[0, 2], h[1, 2]
    rx, ry = residual[:, 0], residual[:, 1]
    dof = max(float((w00 + w11).sum()) - 3.0, 1.0)
    # a floor of (1 cm)^2: landmarks that coincide exactly (constructed scans) must not give an infinite information
    sigma2 = max(float((w00 * rx * rx + 2.0 * w01 * rx * ry + w11 * ry * ry).sum()) / dof, 1e-4)
    # information = the scaled registration's plus the prior's, so a direction the landmarks leave free (one straight
    # wall) comes out as loose as the prior instead of singular
    k_t, k_r = ((config.position_scale, config.heading_scale) if motion_compensated
                else (config.rigid_position_scale, config.rigid_heading_scale))
    s_inv = 1.0 / np.sqrt(np.array([k_t, k_t, k_r]))
    information = h / sigma2 * np.outer(s_inv, s_inv) + config.prior_information
    cov = np.linalg.inv(information)
    cov = 0.5 * (cov + cov.T)
    # never a non-finite number (it would not serialise) nor a matrix that is no covariance (a filter would diverge)
    if not np.isfinite(cov).all() or not np.linalg.eigvalsh(cov)[0] > 0.0:
        return None
    return cov


def landmark_information(dst_xy_m: np.ndarray, which: np.ndarray, tree: cKDTree,
                         config: PoseCovarianceConfig = PoseCovarianceConfig()) -> np.ndarray:
    """What each of the landmarks ``dst_xy_m[which]`` pins (module docstring, ``W_i``): (len(which), 2, 2) float64,
    I for a landmark with fewer than 3 neighbours within ``neighbourhood_m`` (its nearest ``neighbours``, itself
    included) or a round cluster of them, n n^T + (l1 / l2) t t^T for a stretch of a line."""
    dst = np.asarray(dst_xy_m, np.float64).reshape(-1, 2)
    dist, idx = tree.query(dst[which], k=config.neighbours, distance_upper_bound=config.neighbourhood_m)
    near = np.isfinite(dist)  # (n, k); a missing neighbour has the index len(dst)
    count = near.sum(1)
    pts = dst[np.minimum(idx, len(dst) - 1)]
    w = near / np.maximum(count, 1)[:, None]
    mx, my = (w * pts[..., 0]).sum(1), (w * pts[..., 1]).sum(1)
    dx, dy = pts[..., 0] - mx[:, None], pts[..., 1] - my[:, None]
    sxx, syy, sxy = (w * dx * dx).sum(1), (w * dy * dy).sum(1), (w * dx * dy).sum(1)
    # the 2 x 2 scatter's eigen-decomposition in closed form: l2 >= l1 >= 0, the tangent at angle phi
    half, mean = 0.5 * (sxx - syy), 0.5 * (sxx + syy)
    root = np.hypot(half, sxy)
    l1, l2 = mean - root, mean + root
    phi = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    tx, ty = np.cos(phi), np.sin(phi)
    ratio = np.clip(np.divide(l1, l2, out=np.ones_like(l2), where=l2 > 0), 0.0, 1.0)
    # W = n n^T + ratio t t^T with n = (-ty, tx)
    out = np.empty((len(count), 2, 2))
    out[:, 0, 0] = ty * ty + ratio * tx * tx
    out[:, 1, 1] = tx * tx + ratio * ty * ty
    out[:, 0, 1] = out[:, 1, 0] = (ratio - 1.0) * tx * ty
    out[count < 3] = np.eye(2)
    return out


def rotate_covariance(cov: np.ndarray, yaw_rad: float) -> np.ndarray:
    """A (3, 3) pose covariance (x, y, yaw) expressed in a frame turned by ``yaw_rad``: the position block rotated,
    the heading variance unchanged (e.g. keyframe frame -> map frame with ``T_map_keyframe``'s heading)."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    a = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out = a @ np.asarray(cov, np.float64).reshape(3, 3) @ a.T
    return 0.5 * (out + out.T)
