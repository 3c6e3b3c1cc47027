"""Tracking mode: localize a vehicle that was localized a moment ago, from a pose prior instead of the map.

A prior (the previous pose composed with odometry, or any pose with an uncertainty) replaces retrieval:

1. candidates are the ``max_candidates`` keyframes nearest to the prior within its gate (``gate_sigmas`` x
   sigma, plus ``search_radius_m`` of overlap), nearest first;
2. each is registered by nearest-landmark association started at the prior's relative pose
   (``T_keyframe_query = T_keyframe_map * T_map_prior``), with association radii shrinking from the prior's
   uncertainty (2 sigma, capped at ``max_start_radius_m``) to the global estimator's final radius, and
   least-squares rigid fits repeated at each radius until the pose stops moving - no descriptors, no
   hypotheses, a few KD-tree queries;
3. the answer must pass the global localizer's own bar (``min_inliers`` and the aligned-landmark ratio), a
   sequence-consistency check (it lies within the gate of the prior in position and heading), a reversal
   check (``Localizer._reversal_fits_as_well``: turned by 180 degrees it must align fewer landmarks) and a
   turn check (``Localizer._turn_fits_as_well``: no heading outside the prior's gate, within 45 degrees, may
   align as many landmarks);
4. otherwise tracking is lost and the caller falls back to global localization (``Localizer.localize``).

The registration only finds the pose when it starts within its first association radius of it: a prior is
worth tracking from only while that radius covers the prior's uncertainty (``TrackingConfig.covers``: 2 sigma
<= ``max_start_radius_m``, i.e. sigma <= 3 m), and only while its heading is known to within what the
registration turns through (2 sigma <= ``max_start_yaw_rad``, 10 degrees, i.e. sigma <= 5 degrees: a turn
moves landmarks 50 m out by 0.9 m per degree). Measured on ``loop-sim`` (157 revisit queries, prior at the true
position, sigma 1 m, heading off by delta; docs/BENCHMARKS.md "Session 22"): from 15 degrees off 153 of 157
tracked answers lie within 2 m / 2 degrees, from 20 degrees 69-80, from 30 degrees 4-6 with 6-9 wrong, and a
prior turned by 180 degrees with its heading left open was tracked to the reversed heading 10 times. A looser
prior - a last pose with no odometry since, or a long stretch of odometry without a fix - is a place to check,
not a prediction: the caller localizes globally.
Measured on the QA drives (14 scans, prior placed behind the true pose along the road; docs/SERVICE.md,
"Tracking mode"): with the converging registration every prior up to 2 sigma behind gives the pose within
0.25 m; beyond its radius the registration stays near the prior (1.9-7.5 m off), which no gate of the prior
itself can catch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.se2 import compose, inverse, wrap_angle
from reradar_core.localization.confidence import landmark_spread_m
from reradar_core.matching import LandmarkGrid, refine_pose
from reradar_core.matching.motion import MotionConfig, odometry_twist

__all__ = ["PosePrior", "TrackingConfig", "tracking_candidates", "register_from_prior", "Registration"]


@dataclass(frozen=True)
class PosePrior:
    """Where the vehicle should be: a map-frame pose and its uncertainty.

    Attributes:
        T_map_query: (3,) float64 (x m, y m, yaw rad), map frame.
        sigma_xy_m: standard deviation of the position, metres (> 0).
        sigma_yaw_rad: standard deviation of the heading, radians (> 0).
        timestamp_us: the scan time this pose is at (microseconds), or None (unknown): with the next scan's time
            it turns odometry into a speed (``moved``).
        twist: (3,) float64 the vehicle's motion when it reached this pose (vx m/s, vy m/s, yaw rate rad/s, body
            frame; ``matching.motion.odometry_twist``), or None: the motion compensation's prior for a scan
            tracked from this prior (a vehicle standing still or reversing is then fitted from its own motion).
    """

    T_map_query: np.ndarray
    sigma_xy_m: float
    sigma_yaw_rad: float
    timestamp_us: int | None = None
    twist: np.ndarray | None = None

    def __post_init__(self) -> None:
        pose = np.asarray(self.T_map_query, np.float64).reshape(-1)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise ConfigError(f"a pose prior needs a finite (x, y, yaw), got {self.T_map_query!r}")
        for name in ("sigma_xy_m", "sigma_yaw_rad"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise ConfigError(f"prior {name} must be a number, got {value!r}")
        if not (self.sigma_xy_m > 0 and self.sigma_yaw_rad > 0 and math.isfinite(self.sigma_xy_m)
                and math.isfinite(self.sigma_yaw_rad)):
            raise ConfigError(f"prior sigmas must be positive and finite, got {self.sigma_xy_m}, "
                              f"{self.sigma_yaw_rad}")
        object.__setattr__(self, "T_map_query", pose)
        if self.twist is not None:
            twist = np.asarray(self.twist, np.float64).reshape(-1)
            if twist.shape != (3,) or not np.all(np.isfinite(twist)):
                raise ConfigError(f"a prior's motion needs a finite (vx, vy, yaw rate), got {self.twist!r}")
            if not _drive_twist(twist):  # QA session 40: a library caller's 1e9 m/s was taken
                limits = MotionConfig()
                raise ConfigError(f"a prior's motion must be a drive's: at most {limits.max_speed_mps:g} m/s and "
                                  f"{limits.max_yaw_rate_radps:g} rad/s, got (vx, vy, yaw rate) = {tuple(twist)} "
                                  "(m/s, m/s, rad/s; a yaw rate in degrees?)")
            object.__setattr__(self, "twist", twist)
        if self.timestamp_us is not None:
            # an int64 of microseconds, as every scan time here (a float only when whole: 1.7 us is no scan time)
            given = self.timestamp_us
            whole = isinstance(given, (int, np.integer)) or (isinstance(given, (float, np.floating))
                                                            and math.isfinite(given) and float(given).is_integer())
            if not whole or not -(2**63) <= int(given) < 2**63:
                raise ConfigError(f"a prior's timestamp_us must be a 64-bit integer, got {given!r}")
            object.__setattr__(self, "timestamp_us", int(given))

    def moved(self, T_prev_curr: np.ndarray, sigma_growth: float = 0.1, min_sigma_xy_m: float = 0.5,
              min_sigma_yaw_rad: float = math.radians(1.0), timestamp_us: int | None = None,
              motion_config: MotionConfig | None = None) -> PosePrior:
        """The prior after relative motion ``T_prev_curr`` (odometry, in this pose's frame): composed pose,
        sigmas grown by ``sigma_growth`` x distance travelled (and the heading sigma by that x turn, wrapped: a
        turn given as 350 degrees is one of -10, QA session 23). With the new scan's ``timestamp_us`` and this
        pose's, the odometry over the time between them is the new prior's ``twist`` (``odometry_twist`` under
        ``motion_config``, default ``MotionConfig()``: None when the scans are more than ``max_keyframe_gap_s``
        apart, out of order, or the motion is no vehicle's)."""
        motion = np.asarray(T_prev_curr, np.float64).reshape(3)
        dist = float(np.hypot(motion[0], motion[1]))
        turn = abs(float(wrap_angle(motion[2])))
        twist = None
        if timestamp_us is not None and self.timestamp_us is not None:
            twist = odometry_twist(motion, (int(timestamp_us) - self.timestamp_us) * 1e-6,
                                   motion_config or MotionConfig())
            if twist is not None and not _drive_twist(twist):  # a config allowing more than a prior takes
                twist = None
        return PosePrior(compose(self.T_map_query, motion),
                         max(min_sigma_xy_m, self.sigma_xy_m + sigma_growth * dist),
                         max(min_sigma_yaw_rad, self.sigma_yaw_rad + sigma_growth * turn), timestamp_us, twist)


def _drive_twist(twist: np.ndarray) -> bool:
    """``twist`` (vx m/s, vy m/s, yaw rate rad/s) is a drive's motion by ``MotionConfig``'s default limits (60 m/s,
    3 rad/s), what ``odometry_twist`` accepts by default."""
    limits = MotionConfig()
    return bool(math.hypot(twist[0], twist[1]) <= limits.max_speed_mps and abs(twist[2]) <= limits.max_yaw_rate_radps)


@dataclass(frozen=True)
class TrackingConfig:
    """Tracking-mode settings (metres, radians).

    Attributes:
        max_candidates: keyframes nearest to the prior that are registered (2: the nearest and its neighbour,
            in case the nearest one saw the place from a bad angle).
        gate_sigmas: candidates and answers must lie within this many prior sigmas (position and heading).
        search_radius_m: a keyframe this far from the prior still overlaps the scan (radar range >> 20 m).
        min_gate_m: the smallest position gate (a tight prior still allows a keyframe spacing of slack).
        min_gate_yaw_rad: the smallest heading gate.
        final_radius_m: association radius of the last refinement steps (the global estimator's 0.75 m).
        max_start_radius_m: the first association radius is 2 sigma of the prior, capped here; a prior whose
            2 sigma exceeds it is not tracked from (``covers``).
        max_start_yaw_rad: a prior whose heading's 2 sigma exceeds this is not tracked from (``covers``): the
            registration starts at the prior's heading and does not turn further (10 degrees: the explicit
            prior's default sigma of 5 degrees is tracked from; an unknown heading is localized globally).
        turn_check_rad / turn_check_step_rad: the turn check (``Localizer._turn_fits_as_well``): the tracked answer
            turned about the sensor by every multiple of the step up to this angle either way is scored like the
            pose hypotheses; when a heading outside the prior's heading gate aligns as many landmarks as the answer
            does, the prior's heading is contradicted and the scan is localized globally (45 and 1 degrees: a
            landmark 50 m out moves 0.9 m per degree, within the 1.5 m score radius).
    """

    max_candidates: int = 2
    gate_sigmas: float = 3.0
    search_radius_m: float = 20.0
    min_gate_m: float = 2.0
    min_gate_yaw_rad: float = math.radians(5.0)
    final_radius_m: float = 0.75
    max_start_radius_m: float = 6.0
    max_start_yaw_rad: float = math.radians(10.0)
    turn_check_rad: float = math.radians(45.0)
    turn_check_step_rad: float = math.radians(1.0)

    def __post_init__(self) -> None:
        if self.max_candidates < 1 or self.gate_sigmas <= 0 or self.search_radius_m < 0:
            raise ConfigError(f"invalid tracking configuration {self}")
        if self.final_radius_m <= 0 or self.max_start_radius_m < self.final_radius_m:
            raise ConfigError("tracking radii must satisfy 0 < final_radius_m <= max_start_radius_m")
        if not 0 < self.max_start_yaw_rad <= math.pi:
            raise ConfigError(f"max_start_yaw_rad must lie in (0, pi], got {self.max_start_yaw_rad}")
        if not (0 <= self.turn_check_rad <= math.pi and self.turn_check_step_rad > 0):
            raise ConfigError("turn_check_rad must lie in [0, pi] and turn_check_step_rad be > 0, got "
                              f"{self.turn_check_rad} and {self.turn_check_step_rad}")

    def covers(self, prior: PosePrior) -> bool:
        """Whether the registration reaches the whole of ``prior``'s likely error (2 sigma <= the capped first
        association radius, and 2 heading sigmas <= ``max_start_yaw_rad``). When it does not, a tracked answer
        may be a pose near the prior that is not the vehicle's - or the vehicle's place at the reversed
        heading of a symmetric street - inside the prior's wide gate: such a prior must not be tracked from
        (localize globally)."""
        return (2.0 * prior.sigma_xy_m <= self.max_start_radius_m
                and 2.0 * prior.sigma_yaw_rad <= self.max_start_yaw_rad + 1e-12)

    def position_gate_m(self, prior: PosePrior) -> float:
        return max(self.min_gate_m, self.gate_sigmas * prior.sigma_xy_m)

    def yaw_gate_rad(self, prior: PosePrior) -> float:
        return max(self.min_gate_yaw_rad, self.gate_sigmas * prior.sigma_yaw_rad)

    def radii(self, prior: PosePrior) -> tuple[float, ...]:
        """Association radii, coarse to fine, metres: from 2 sigma of the prior (at least 2 m, at most
        ``max_start_radius_m``) halving to the final radius, each radius once (``register_from_prior`` iterates at each one until the pose settles)."""
        start = min(self.max_start_radius_m, max(2.0, 2.0 * prior.sigma_xy_m))
        out = [start]
        while out[-1] / 2 > self.final_radius_m:
            out.append(out[-1] / 2)
        return (*out, self.final_radius_m) if out[-1] > self.final_radius_m else tuple(out)


def tracking_candidates(poses: np.ndarray, prior: PosePrior, config: TrackingConfig) -> np.ndarray:
    """Indices of the keyframes (rows of (N, 3) ``poses``) within the prior's gate plus ``search_radius_m``,
    nearest first, at most ``config.max_candidates``."""
    d = np.hypot(poses[:, 0] - prior.T_map_query[0], poses[:, 1] - prior.T_map_query[1])
    near = np.flatnonzero(d <= config.position_gate_m(prior) + config.search_radius_m)
    return near[np.argsort(d[near], kind="stable")][: config.max_candidates]


@dataclass
class Registration:
    """Result of ``register_from_prior``: ``T_keyframe_query`` (x m, y m, yaw rad), query landmarks within the
    final radius of a keyframe landmark (``num_inliers``), their fraction of the query's landmarks, and their
    spatial spread in the query's sensor frame (``confidence.landmark_spread_m``, metres; the confidence cue)."""

    T_keyframe_query: np.ndarray
    num_inliers: int
    inlier_ratio: float
    inlier_spread_m: float = 0.0


#: a registration step that moves the pose less than this (metres; and ``CONVERGED_STEP_M`` / 20 m of heading,
#: radians) ends the steps at its radius
CONVERGED_STEP_M = 0.005
#: most association + fit steps at one radius
MAX_STEPS_PER_RADIUS = 25


def register_from_prior(query: ScanFeatures, grid: LandmarkGrid, T_keyframe_query: np.ndarray,
                        radii: tuple[float, ...], max_steps: int = MAX_STEPS_PER_RADIUS,
                        converged_m: float = CONVERGED_STEP_M) -> Registration:
    """Refine ``T_keyframe_query`` by iterated nearest-landmark association with ``grid``'s landmarks within
    the given shrinking radii and a least-squares rigid fit per step (``matching.refine_pose``, the guided
    estimator's refinement); inliers are counted at the last radius. A step that associates fewer than 3
    landmarks ends the registration as failed (0 inliers).

    At each radius the steps repeat until one moves the pose less than ``converged_m`` (heading: that over
    20 m, the scale of the landmarks' lever arm) or ``max_steps`` were taken. One step per radius (before)
    recovers only about half of an offset along a road, whose kerbs and facades pull the scan sideways far
    more than along: from a prior 1 m behind the truth the answer was 0.3-0.6 m off, from 2 m 1.4-1.9 m off,
    every one accepted (the QA drives of ``docs/SERVICE.md``, "Tracking mode").
    """
    src = np.asarray(query.keypoints_xy_m, np.float64).reshape(-1, 2)
    n = len(src)
    pose = np.asarray(T_keyframe_query, np.float64).reshape(3).copy()
    if n < 3 or len(grid.points) < 3:
        return Registration(pose, 0, 0.0)
    mask = np.zeros(n, bool)
    for radius in radii:
        for _ in range(max(1, max_steps)):
            new, mask = refine_pose(src, grid, pose, (radius,))
            if int(mask.sum()) < 3:  # lost the map: a failed registration, whatever an earlier radius aligned
                return Registration(pose, 0, 0.0)
            moved = float(np.hypot(new[0] - pose[0], new[1] - pose[1]))
            turned = abs(float(wrap_angle(new[2] - pose[2])))
            pose = new
            if moved < converged_m and turned * 20.0 < converged_m:
                break
    k = int(mask.sum())
    pose = np.array([pose[0], pose[1], wrap_angle(pose[2])])
    return Registration(pose, k, k / n, landmark_spread_m(src[mask]))


def within_gate(T_map_query: np.ndarray, prior: PosePrior, config: TrackingConfig) -> bool:
    """Sequence consistency: the answer lies within the prior's position and heading gates."""
    dxy = float(np.hypot(*(np.asarray(T_map_query[:2]) - prior.T_map_query[:2])))
    dyaw = abs(float(wrap_angle(T_map_query[2] - prior.T_map_query[2])))
    return dxy <= config.position_gate_m(prior) and dyaw <= config.yaw_gate_rad(prior)


def relative_to_keyframe(T_map_keyframe: np.ndarray, prior: PosePrior) -> np.ndarray:
    """The prior's pose in the keyframe's sensor frame: ``T_keyframe_map * T_map_prior``."""
    return compose(inverse(T_map_keyframe), prior.T_map_query)
