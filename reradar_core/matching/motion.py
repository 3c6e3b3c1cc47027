"""Motion compensation of an answer's pose: both scans de-skewed, the query's motion fitted with its pose.

A scanning radar turns once per sweep (0.25 s at 4 Hz) while the vehicle moves, so every azimuth is seen from the
pose at its own time: at 10 m/s a landmark ahead is seen 1.25 m from where a landmark behind would put it, and in
a turn at 40 deg/s the first and last azimuths are 10 deg apart. A rigid registration of two such sweeps aligns
their mid-sweep poses only where the two distortions cancel (same direction, speed and turn); a revisit driven the
other way, or a turn, keeps part of them as pose error. Measured on the benchmark's `loop-sim-hard` queries with
the true motion of both drives (docs/BENCHMARKS.md "Session 29"): de-skewing both scans cut the mean translation
error from 0.25 m to 0.08 m and the heading error from 0.29 to 0.21 deg; de-skewing one side only made both worse.

So, after an answer is chosen (its decision, confidence and cues untouched), ``motion_polish``:

1. de-skews the map keyframe's landmarks with its own motion (``keyframe_twists``: the map drive's keyframe poses
   and times, neighbours in time within ``max_keyframe_gap_s``);
2. fits the query's pose *and* its motion (body-frame velocity and yaw rate, constant over the sweep) to them by
   Gauss-Newton with nearest-landmark association at shrinking radii, each query landmark moved by its own time
   offset from mid-sweep (``azimuth_time_offsets``). The motion is observable only through landmarks at many
   azimuths, and a forward speed mimics a turn for landmarks abeam (a street's two sides are seen a half sweep
   apart), so the motion has a prior: forward speed around the map drive's speed at that keyframe (vehicles
   pass a place at similar speeds; ``speed_sigma_mps``), no sideways speed (a car does not slide;
   ``lateral_speed_sigma_mps``), a weak yaw-rate prior (``yaw_rate_sigma_radps``).

With the motion fitted rather than known, the benchmark's `loop-sim-hard` answers go from 0.251 m / 0.294 deg to
0.070 m / 0.225 deg (docs/BENCHMARKS.md "Session 29"; the priors chosen on the training splits). The Gauss-Newton
rounds run compiled (``motion_kernels``, ~1.3 ms an answer) when numba is there.

The rigid answer is kept when the map's motion at the keyframe is unknown (no keyframe within
``max_keyframe_gap_s``, or one whose heading turned more than 90 deg), when the fit associates fewer landmarks at the
last radius than the rigid pose does with the scans as seen (``min_fit_share``: a fit that settled on a wrong
motion), when an input is not finite, or when the fit moves the pose more than ``max_shift_m`` or a sweep's travel
(whichever is more) / ``max_turn_rad`` (a compensation is a correction of at most a sweep's travel, not a new
answer). A tracked scan brings the vehicle's own motion (its odometry over the time between its scans,
``odometry_twist``), which then centres the prior instead of the map drive's speed (``src_twist``).

Frames and conventions (docs/CONVENTIONS.md): sensor frame x forward, y left; azimuth a clockwise from +x,
azimuth index k at time t0 + k T / A, mid-sweep at t0 + (A - 1) / 2 * T / A; a twist is (vx m/s, vy m/s,
yaw rate rad/s) in the body frame at mid-sweep.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from reradar_core.errors import ConfigError
from reradar_core.geometry.se2 import relative_pose, transform_points, wrap_angle
from reradar_core.jit import jit_enabled

__all__ = ["MotionConfig", "MotionPolish", "azimuth_time_offsets", "deskew_points", "deskewed", "keyframe_twists",
           "motion_polish", "odometry_twist", "time_neighbours"]


@dataclass(frozen=True)
class MotionConfig:
    """Settings of the motion-compensated pose (``motion_polish``); seconds, metres, radians.

    Attributes:
        enabled: compensate the answers' poses (False: the rigid registration's pose, as before session 29).
        sweep_period_s, num_azimuths: the radar's sweep (every Navtech preset here: 0.25 s, 400 azimuths).
        max_keyframe_gap_s: a map keyframe's motion is taken from its neighbours in time within this gap (2 s);
            a keyframe with none is not compensated (the answer keeps its rigid pose).
        max_speed_mps, max_yaw_rate_radps: a keyframe motion faster than these (60 m/s, 3 rad/s) is not a drive's
            (keyframes with made-up times, or poses from two drives interleaved): its motion counts as unknown.
        speed_sigma_mps: prior on the query's forward speed, around the map drive's speed at the keyframe, or around
            the vehicle's own (a tracked scan's odometry, ``motion_polish``'s ``src_twist``) (3 m/s).
        lateral_speed_sigma_mps: prior on its sideways speed, around 0 or the odometry's (0.3 m/s: a car does not
            slide).
        yaw_rate_sigma_radps: prior on its yaw rate, around 0 or the odometry's (1 rad/s: weak; a U-turn is ~0.8).
        radii_m: association radii of the Gauss-Newton rounds, coarse to fine: from 3 m, because on a drive the
            other way at 20-30 m/s the rigid pose is 1.4-2.8 m off along the track (each sweep's skew pulls the
            other way) and a fit whose first association is narrower cannot reach the right pose (session 30),
            down to the pose polish's 0.75-0.4 m.
        iterations: Gauss-Newton steps per radius.
        min_associated: landmarks that must associate at the last radius.
        min_fit_share: the compensated pose must associate at the last radius at least this share of what the rigid
            pose associates there with the scans as seen (1.0: at least as many; a fit that settled on a wrong
            motion, e.g. a sweep in which a U-turn begins, associates fewer and the rigid pose is kept).
        max_shift_m, max_turn_rad: a fit that moves the rigid pose farther is discarded; the shift allowed is
            max(``max_shift_m``, a sweep's travel at the larger of the map drive's and the query's measured speed)
            (7.5 m at 30 m/s).
        Bounds (checked): sigmas 1e-4..1e4, radii decreasing and at most 10 m, at most 50 iterations and 100
        Gauss-Newton steps (radii x iterations), min_associated 3..10,000, a sweep of at most 10 s and 100,000
        azimuths (a typo must fail at start-up, not slow or silence every answer).
        The priors were chosen on the training splits' unseen sessions (docs/BENCHMARKS.md "Session 29").
    """

    enabled: bool = True
    sweep_period_s: float = 0.25
    num_azimuths: int = 400
    max_keyframe_gap_s: float = 2.0
    max_speed_mps: float = 60.0
    max_yaw_rate_radps: float = 3.0
    speed_sigma_mps: float = 3.0
    lateral_speed_sigma_mps: float = 0.3
    yaw_rate_sigma_radps: float = 1.0
    radii_m: tuple[float, ...] = (3.0, 2.0, 1.5, 1.0, 0.75, 0.6, 0.5, 0.4)
    iterations: int = 3
    min_associated: int = 12
    min_fit_share: float = 1.0
    max_shift_m: float = 3.0
    max_turn_rad: float = math.radians(3.0)

    def __post_init__(self) -> None:
        numbers = (self.sweep_period_s, self.max_keyframe_gap_s, self.max_speed_mps, self.max_yaw_rate_radps,
                   self.speed_sigma_mps, self.lateral_speed_sigma_mps, self.yaw_rate_sigma_radps, self.max_shift_m,
                   self.max_turn_rad, *self.radii_m)
        if not all(math.isfinite(v) for v in numbers):
            raise ConfigError("the motion settings must be finite numbers")
        if not 0.0 < self.min_fit_share <= 1.0:
            raise ConfigError(f"min_fit_share must be in (0, 1], got {self.min_fit_share}")
        if self.sweep_period_s <= 0 or self.num_azimuths < 1 or self.max_keyframe_gap_s <= 0:
            raise ConfigError("sweep_period_s and max_keyframe_gap_s must be positive and num_azimuths >= 1")
        if min(self.speed_sigma_mps, self.lateral_speed_sigma_mps, self.yaw_rate_sigma_radps) <= 0:
            raise ConfigError("the motion priors' sigmas must be positive")
        if not self.radii_m or min(self.radii_m) <= 0 or self.iterations < 1 or self.min_associated < 3:
            raise ConfigError("radii_m must be positive radii, iterations >= 1 and min_associated >= 3")
        if self.max_shift_m <= 0 or self.max_turn_rad <= 0 or self.max_speed_mps <= 0 or self.max_yaw_rate_radps <= 0:
            raise ConfigError("max_shift_m, max_turn_rad, max_speed_mps and max_yaw_rate_radps must be positive")
        # upper bounds: 1 / sigma^2 must not overflow, and no setting may make every answer slow
        if max(self.speed_sigma_mps, self.lateral_speed_sigma_mps, self.yaw_rate_sigma_radps) > 1e4 or min(
                self.speed_sigma_mps, self.lateral_speed_sigma_mps, self.yaw_rate_sigma_radps) < 1e-4:
            raise ConfigError("the motion priors' sigmas must be between 1e-4 and 1e4")
        if any(b >= a for a, b in zip(self.radii_m, self.radii_m[1:], strict=False)):
            raise ConfigError(f"radii_m must run coarse to fine (each radius smaller than the one before), got "
                              f"{self.radii_m}")
        if (max(self.radii_m) > 10.0 or len(self.radii_m) * self.iterations > 100 or self.iterations > 50
                or self.min_associated > 10_000):
            raise ConfigError("radii_m must be at most 10 m, iterations at most 50, len(radii_m) x iterations at "
                              "most 100 Gauss-Newton steps (default 24) and min_associated at most 10000")
        if self.sweep_period_s > 10.0 or self.num_azimuths > 100_000:
            raise ConfigError("sweep_period_s must be at most 10 s and num_azimuths at most 100000")


@dataclass(frozen=True)
class MotionPolish:
    """A motion-compensated pose.

    Attributes:
        T_dst_src: (3,) float64 pose of the source scan (mid-sweep) in the destination keyframe's frame.
        twist: (3,) float64 the source scan's fitted motion (vx m/s, vy m/s, yaw rate rad/s), body frame.
        num_associated: landmarks associated at the last radius.
    """

    T_dst_src: np.ndarray
    twist: np.ndarray
    num_associated: int


def azimuth_time_offsets(xy_m: np.ndarray, config: MotionConfig = MotionConfig()) -> np.ndarray:
    """(N, 2) landmark positions in the sensor frame (x forward, y left, metres) -> (N,) float64 time of the azimuth
    each lies at, relative to mid-sweep, seconds (in [-T/2, T/2]; azimuth 0 = straight ahead, seen first)."""
    xy = np.asarray(xy_m, np.float64).reshape(-1, 2)
    a = np.mod(np.arctan2(-xy[:, 1], xy[:, 0]), 2.0 * np.pi)  # clockwise from +x
    t, n = config.sweep_period_s, config.num_azimuths
    return a / (2.0 * np.pi) * t - (n - 1) / (2.0 * n) * t


def deskew_points(xy_m: np.ndarray, tau_s: np.ndarray, twist: np.ndarray) -> np.ndarray:
    """Move (N, 2) points seen at time offsets ``tau_s`` (N,) from a sensor moving with ``twist`` (vx, vy, yaw rate;
    body frame at mid-sweep) into the mid-sweep sensor frame: R(w tau) p + v tau (first order in tau: the sweep's
    turn is at most a few degrees). Returns (N, 2) float64 metres."""
    xy = np.asarray(xy_m, np.float64).reshape(-1, 2)
    tau = np.asarray(tau_s, np.float64).reshape(-1)
    vx, vy, w = (float(v) for v in np.asarray(twist, np.float64).reshape(3))
    c, s = np.cos(w * tau), np.sin(w * tau)
    return np.column_stack([c * xy[:, 0] - s * xy[:, 1] + vx * tau, s * xy[:, 0] + c * xy[:, 1] + vy * tau])


def deskewed(xy_m: np.ndarray, twist: np.ndarray, config: MotionConfig = MotionConfig()) -> np.ndarray:
    """(N, 2) landmarks of one sweep, as seen (sensor frame, metres), moved into its mid-sweep frame: each by its
    azimuth's time (``azimuth_time_offsets``) and the sweep's motion ``twist`` (``deskew_points``)."""
    return deskew_points(xy_m, azimuth_time_offsets(xy_m, config), twist)


def keyframe_twists(poses: np.ndarray, timestamps_us: np.ndarray,
                    config: MotionConfig = MotionConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Each map keyframe's motion from its neighbours in time (the map drive's own poses).

    Args:
        poses: (N, 3) ``T_map_keyframe`` (x m, y m, yaw rad) at mid-sweep.
        timestamps_us: (N,) scan times, microseconds (any order; keyframes of one drive).
    Returns:
        (N, 3) float64 twists (vx m/s, vy m/s, yaw rate rad/s; body frame: constant motion along the arc between
        the neighbours, exact for a constant turn) and (N,) bool: known (a neighbour in time within
        ``max_keyframe_gap_s``; central difference when both are, one-sided otherwise; the heading turning less than
        90 deg between them; within ``max_speed_mps`` and ``max_yaw_rate_radps``). Unknown rows are 0.
    """
    poses = np.asarray(poses, np.float64).reshape(-1, 3)
    t = np.asarray(timestamps_us, np.int64).reshape(-1)
    n = len(t)
    twists = np.zeros((n, 3), np.float64)
    known = np.zeros(n, bool)
    if n < 2:
        return twists, known
    # every keyframe at once, in time order (a map may hold 100,000: a loop over them cost ~3 s)
    order, has_before, has_after = time_neighbours(t, config.max_keyframe_gap_s)
    ts = t[order]
    j = np.arange(n)
    i0 = np.where(has_before, j - 1, j)  # sorted positions of the two ends: the neighbours, or k itself
    i1 = np.where(has_after, j + 1, j)
    ok = has_before | has_after
    dt = np.where(ok, (ts[i1] - ts[i0]) * 1e-6, 1.0)
    chord = relative_pose(poses[order[i0]], poses[order[i1]])  # in i0's frame; heading change wrapped to (-pi, pi]
    found, plausible = _arc_twists(chord, dt, config)
    ok &= plausible
    twists[order[ok]] = found[ok]
    known[order] = ok
    return twists, known


def time_neighbours(timestamps_us: np.ndarray, max_gap_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which scans of one drive have a neighbour in time within ``max_gap_s`` (a later time, not an equal one).

    Args:
        timestamps_us: (N,) int64 scan times, microseconds, any order.
    Returns:
        (N,) int64 the stable time order, and (N,) bool each (in that order): a neighbour before, one after.
    """
    t = np.asarray(timestamps_us, np.int64).reshape(-1)
    order = np.argsort(t, kind="stable")
    gaps = np.diff(t[order])
    close = (gaps > 0) & (gaps <= max_gap_s * 1e6)  # between sorted scans j and j + 1
    return order, np.concatenate([[False], close]), np.concatenate([close, [False]])


def _arc_twists(chord: np.ndarray, dt_s: np.ndarray, config: MotionConfig) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) constant motions (vx m/s, vy m/s, yaw rate rad/s; body frame) that move a pose by ``chord`` ((N, 3),
    in the first pose's frame, heading change wrapped) in ``dt_s`` (N,) seconds (> 0), and (N,) bool: plausible (a
    turn of at most 90 deg between the ends, within ``max_speed_mps`` and ``max_yaw_rate_radps``)."""
    turn = chord[:, 2]
    # under constant motion the chord runs along the heading halfway between its ends, and its length is the arc's
    # times sinc(turn / 2); that heading is the body frame of every pose on the arc
    c, s = np.cos(turn / 2), np.sin(turn / 2)
    stretch = 1.0 / np.sinc(turn / (2 * np.pi))  # (turn / 2) / sin(turn / 2), 1 at no turn
    found = np.column_stack([(c * chord[:, 0] + s * chord[:, 1]) / dt_s * stretch,
                             (-s * chord[:, 0] + c * chord[:, 1]) / dt_s * stretch, turn / dt_s])
    # ends turned more than 90 deg apart cannot say how it turned between them; faster is no drive's motion
    plausible = ((np.abs(turn) <= math.pi / 2) & (np.hypot(found[:, 0], found[:, 1]) <= config.max_speed_mps)
                 & (np.abs(found[:, 2]) <= config.max_yaw_rate_radps))
    return found, plausible


def odometry_twist(T_prev_curr: np.ndarray, dt_s: float, config: MotionConfig = MotionConfig()) -> np.ndarray | None:
    """The vehicle's motion from its odometry between two scans: (3,) float64 (vx m/s, vy m/s, yaw rate rad/s; body
    frame, constant along the arc; negative vx in reverse gear, 0 standing still), or None when ``dt_s`` is not in
    (0, ``max_keyframe_gap_s``], the odometry is not finite, or the motion is implausible (as ``keyframe_twists``).

    Args:
        T_prev_curr: (3,) the odometry (x m, y m, yaw rad) in the previous scan's frame.
        dt_s: seconds between the two scans.
    """
    chord = np.asarray(T_prev_curr, np.float64).reshape(1, 3).copy()
    if not (np.isfinite(chord).all() and math.isfinite(dt_s) and 0.0 < dt_s <= config.max_keyframe_gap_s):
        return None
    chord[0, 2] = wrap_angle(float(chord[0, 2]))
    found, plausible = _arc_twists(chord, np.array([dt_s]), config)
    return found[0] if plausible[0] else None


def motion_polish(src_xy_m: np.ndarray, dst_xy_m: np.ndarray, T_dst_src: np.ndarray, dst_twist: np.ndarray,
                  config: MotionConfig = MotionConfig(), src_twist: np.ndarray | None = None) -> MotionPolish | None:
    """The source scan's mid-sweep pose in the destination keyframe's frame, both scans' motion compensated.

    Args:
        src_xy_m: (N, 2) the query's landmarks (its sensor frame, metres), as seen (skewed).
        dst_xy_m: (M, 2) the keyframe's landmarks, as seen.
        T_dst_src: (3,) the rigid registration's pose (start of the fit).
        dst_twist: (3,) the keyframe's motion (``keyframe_twists``); its speed is the prior's forward speed.
        src_twist: (3,) the query's motion as the vehicle measured it (``odometry_twist``: a tracked scan), or
            None. Given, it is the prior's mean (forward and sideways speed, yaw rate; same sigmas) and the fit's
            start, in place of the map drive's speed going forward: a vehicle standing still, reversing or driving
            at another speed than the map drive is then fitted from its own motion.
    Returns:
        ``MotionPolish``, or None (keep the rigid pose) when an input is not finite, too few landmarks associate (fewer
        than ``min_associated``, or at the last radius fewer than ``min_fit_share`` of what the rigid pose associates
        with the scans as seen), or the fit moves the pose more than the shift allowed (``MotionConfig.max_shift_m``,
        at least a sweep's travel) / ``max_turn_rad``.
    """
    src = np.asarray(src_xy_m, np.float64).reshape(-1, 2)
    seen = np.asarray(dst_xy_m, np.float64).reshape(-1, 2)
    dst_twist = np.asarray(dst_twist, np.float64).reshape(3)
    start = np.asarray(T_dst_src, np.float64).reshape(3)
    measured = None if src_twist is None else np.asarray(src_twist, np.float64).reshape(3)
    if (len(src) < config.min_associated or len(seen) < config.min_associated or not np.isfinite(src).all()
            or not np.isfinite(seen).all() or not np.isfinite(dst_twist).all() or not np.isfinite(start).all()
            or (measured is not None and not np.isfinite(measured).all())):
        return None
    dst = deskewed(seen, dst_twist, config)
    # what the rigid pose associates at the last radius with the scans as seen: the bar the fit must reach
    rigid_at = transform_points(start, src)
    rigid_count = int(np.isfinite(cKDTree(seen).query(rigid_at, distance_upper_bound=config.radii_m[-1])[0]).sum())
    bar = max(config.min_associated, math.ceil(config.min_fit_share * rigid_count))
    tau = azimuth_time_offsets(src, config)
    map_speed = float(np.hypot(dst_twist[0], dst_twist[1]))
    prior_mean = np.concatenate([np.zeros(3), [map_speed, 0.0, 0.0] if measured is None else measured])
    prior_precision = np.array([0.0, 0.0, 0.0, config.speed_sigma_mps ** -2, config.lateral_speed_sigma_mps ** -2,
                                config.yaw_rate_sigma_radps ** -2])
    prior_hessian = np.diag(prior_precision) + 1e-9 * np.eye(6)
    # a sweep's travel at the map drive's (or the measured query's) speed: how far the skews can have pulled the
    # rigid pose
    max_shift = max(config.max_shift_m,
                    config.sweep_period_s * max(map_speed, float(np.hypot(prior_mean[3], prior_mean[4]))))
    x = np.concatenate([start, prior_mean[3:]])

    def step(x: np.ndarray, src_m: np.ndarray, tau_m: np.ndarray, dst_m: np.ndarray) -> np.ndarray:
        """One Gauss-Newton step on pairs src_m[i] <-> dst_m[i] (first order in tau), with the motion prior."""
        c, s = math.cos(x[2]), math.sin(x[2])
        lm = deskew_points(src_m, tau_m, x[3:])
        residual = (dst_m - transform_points(x[:3], lm)).reshape(-1)  # x0, y0, x1, y1, ...
        # d pred / d params, rows interleaved as the residual: translation, heading, velocity (rotated into the
        # keyframe's frame), yaw rate (rotated)
        jac = np.zeros((2 * len(src_m), 6))
        jac[0::2, 0] = 1.0
        jac[1::2, 1] = 1.0
        jac[0::2, 2] = -s * lm[:, 0] - c * lm[:, 1]
        jac[1::2, 2] = c * lm[:, 0] - s * lm[:, 1]
        jac[0::2, 3], jac[1::2, 3] = c * tau_m, s * tau_m
        jac[0::2, 4], jac[1::2, 4] = -s * tau_m, c * tau_m
        cw, sw = np.cos(x[5] * tau_m), np.sin(x[5] * tau_m)
        px = -(sw * src_m[:, 0] + cw * src_m[:, 1]) * tau_m  # d(R(w tau) p)/dw = tau R'(w tau) p
        py = (cw * src_m[:, 0] - sw * src_m[:, 1]) * tau_m
        jac[0::2, 5], jac[1::2, 5] = c * px - s * py, s * px + c * py
        gradient = jac.T @ residual - prior_precision * (x - prior_mean)
        return x + np.linalg.solve(jac.T @ jac + prior_hessian, gradient)

    # nearest-landmark association at shrinking radii, from the rigid pose and the prior's motion
    if jit_enabled():  # the same rounds compiled (``motion_kernels``); a near-tie look-up takes the numpy path
        from reradar_core.matching.motion_kernels import motion_fit
        from reradar_core.matching.nn_kernels import bucket_landmarks

        fitted, associated, unsure = motion_fit(src, tau, dst, bucket_landmarks(dst, 1.5, 1 << 16), x, prior_mean,
                                                prior_precision, config.radii_m, config.iterations,
                                                config.min_associated)
        if not unsure:
            return _checked(fitted, associated, bar, start, max_shift, config)
    tree = cKDTree(dst)
    associated = 0
    for radius in config.radii_m:
        for _ in range(config.iterations):
            pred = transform_points(x[:3], deskew_points(src, tau, x[3:]))
            dist, idx = tree.query(pred, distance_upper_bound=radius)
            m = np.isfinite(dist)
            associated = int(m.sum())
            if associated < config.min_associated:
                return None
            x = step(x, src[m], tau[m], dst[idx[m]])
    return _checked(x, associated, bar, start, max_shift, config)


def _checked(x: np.ndarray, associated: int, bar: int, start: np.ndarray, max_shift: float,
             config: MotionConfig) -> MotionPolish | None:
    """The fitted parameters as a ``MotionPolish``, or None when fewer than ``bar`` landmarks associated at the last
    radius (``min_associated``, and ``min_fit_share`` of the rigid pose's), the fit is not finite, or the pose moved
    more than ``max_shift`` (m) / ``max_turn_rad`` from the rigid ``start``."""
    if associated < bar or not np.isfinite(x).all():
        return None
    x = np.asarray(x, np.float64).copy()
    x[2] = wrap_angle(float(x[2]))
    if (math.hypot(x[0] - start[0], x[1] - start[1]) > max_shift
            or abs(wrap_angle(float(x[2] - start[2]))) > config.max_turn_rad):
        return None
    return MotionPolish(x[:3].copy(), x[3:].copy(), int(associated))
