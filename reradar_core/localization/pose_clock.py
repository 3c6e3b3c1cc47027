"""Do a map drive's poses run on its scans' clock? Consecutive keyframes registered against each other, compared with
the pose file read at shifted times.

A pose file on another time base than the scans (GPS time against UTC: 18 s; a logger's clock a second off; a
relative clock started elsewhere) passes every check of the file itself: it covers the scans' times, its headings
follow its travel. Each keyframe then gets the pose of another instant - 7 m along the track and 37 degrees off at a
corner for a 1 s offset (QA session 40) - and the map answers every query at that wrong pose, confidently. The scans
themselves say how the vehicle moved between two keyframes: registering keyframe i+1 against keyframe i
(``estimate_pose_guided``, the pose estimator's own method) gives its turn to ~0.2 degrees. The turns the pose file
gives between the same two times agree with those only on the scans' clock; read ``offset`` seconds later they agree
best where ``offset`` is the two clocks' difference:

    check = pose_clock_offset(T_prev_next, times_us, poses, registered)
    check.offset_s          # the shift at which the pose file's turns agree best with the scans' (0 on one clock)
    check.offset_detected   # the pose file is off the scans' clock by more than a sweep: refuse the map

Only turns are compared (a drive at steady speed shows no offset in its distances), so a drive without turns gives no
verdict (``offset_detected`` False). Frames: poses ``T_map_keyframe`` (x m, y m, yaw rad); ``T_prev_next`` the pose of
keyframe i+1 in keyframe i's sensor frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from reradar_core.features import ScanFeatures
from reradar_core.geometry.se2 import relative_pose, wrap_angle
from reradar_core.io.poses import gps_offset_hint
from reradar_core.matching import AlignmentConfig, estimate_pose_guided

__all__ = ["PoseClockConfig", "PoseClockCheck", "consecutive_registrations", "pose_clock_offset",
           "pose_clock_message"]


@dataclass(frozen=True)
class PoseClockConfig:
    """Settings of the pose-clock check (seconds, degrees, counts).

    Attributes:
        max_offset_s: shifts tried, -max ... +max (GPS time runs 18 s ahead of UTC; 30 s covers it).
        coarse_step_s: step of the first search; ``fine_step_s`` around its best.
        min_offset_s: an offset under this is no finding (one sweep, 0.25 s at 4 Hz: within what the mid-sweep poses
            and the motion compensation already account for).
        min_turn_deg: only pairs whose registration turns at least this much are compared (the turns carry the
            clock; the straight pairs between them add only the registrations' noise, and would dilute a long drive's
            few corners).
        min_pairs: such turning pairs that must register (inlier ratio >= ``min_inlier_ratio``, at most
            ``max_pair_gap_s`` apart) for any verdict.
        min_inlier_ratio: a pair's registration counts when this share of keyframe i+1's landmarks align (the
            answers' floor, ``LocalizationConfig.min_inlier_ratio``).
        max_pair_gap_s: pairs further apart in time are skipped (a gap in the recording, not a drive).
        clip_error_deg: a pair's disagreement counts at most this much (a wrong registration, e.g. of two scans
            20 m apart in snow, is one pair's error, not the verdict's).
        min_error_deg: the mean turn disagreement at offset 0 must exceed this for a finding (registrations agree
            with a pose file on their clock to ~0.3 degrees on turning pairs; a drive without turns has none).
        max_error_ratio: and the best shift must bring it below this share of the disagreement at 0.
        min_coverage: a shift counts only when this share of the pairs keeps both shifted times inside the drive.
        tie_deg: shifts whose disagreement is within this of the least are ties, and the smallest of them (in
            magnitude) is taken: a drive that repeats its turns (a slalom, laps of a short loop) agrees again a
            period away, and a pose file is far likelier a second off than a period.
    """

    max_offset_s: float = 30.0
    coarse_step_s: float = 0.25
    fine_step_s: float = 0.05
    min_offset_s: float = 0.25
    min_turn_deg: float = 1.0
    min_pairs: int = 10
    min_inlier_ratio: float = 0.45
    max_pair_gap_s: float = 3.0
    clip_error_deg: float = 10.0
    min_error_deg: float = 0.5
    max_error_ratio: float = 0.5
    min_coverage: float = 0.5
    tie_deg: float = 0.1

    def __post_init__(self) -> None:
        for name in ("max_offset_s", "coarse_step_s", "fine_step_s", "min_offset_s", "min_turn_deg", "max_pair_gap_s",
                     "clip_error_deg", "min_error_deg", "tie_deg"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"PoseClockConfig.{name} must be a positive number, got {getattr(self, name)!r}")
        for name in ("min_inlier_ratio", "max_error_ratio", "min_coverage"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"PoseClockConfig.{name} must lie in (0, 1], got {getattr(self, name)!r}")
        if self.min_pairs < 1:
            raise ValueError(f"PoseClockConfig.min_pairs must be >= 1, got {self.min_pairs!r}")


@dataclass(frozen=True)
class PoseClockCheck:
    """The check's outcome.

    Attributes:
        pairs: consecutive keyframe pairs whose registration counted (turning ones, ``PoseClockConfig.min_turn_deg``).
        error_at_zero_deg: mean |turn from the poses - turn from the scans| (each clipped at
            ``PoseClockConfig.clip_error_deg``) over those pairs, poses read as given.
        offset_s: the shift (seconds; the poses read at scan time + offset) at which that mean is least (a pair the
            shift takes beyond the drive counted as given); 0.0 when no finding.
        error_at_offset_deg: the mean there.
        offset_detected: the poses are off the scans' clock (``PoseClockConfig``'s rule).
    """

    pairs: int
    error_at_zero_deg: float
    offset_s: float
    error_at_offset_deg: float
    offset_detected: bool


def consecutive_registrations(read_keyframe: Callable[[int], ScanFeatures], n: int,
                              config: AlignmentConfig = AlignmentConfig(),
                              on_pair: Callable[[int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Register every keyframe i+1 against keyframe i (``estimate_pose_guided``; 5-25 ms a pair). ``on_pair(i)``
    after each (a build's heartbeat).

    Returns:
        (N-1, 3) float64 ``T_prev_next`` (NaN where the registration failed) and (N-1,) float64 inlier ratios
        (0 where it failed).
    """
    T = np.full((max(n - 1, 0), 3), np.nan)
    ratio = np.zeros(max(n - 1, 0))
    prev = read_keyframe(0) if n else None
    for i in range(n - 1):
        nxt = read_keyframe(i + 1)
        assert prev is not None
        est = estimate_pose_guided(nxt.keypoints_xy_m, nxt.local_descriptors, prev.keypoints_xy_m,
                                   prev.local_descriptors, config)
        if est.success:
            T[i], ratio[i] = est.pose, est.inlier_ratio
        prev = nxt
        if on_pair is not None:
            on_pair(i)
    return T, ratio


def _interpolate(times_us: np.ndarray, poses: np.ndarray, t_us: np.ndarray) -> np.ndarray:
    """Poses (..., 3) at ``t_us`` by linear interpolation between keyframes (yaw on the circle); ``t_us`` inside the
    drive."""
    i = np.clip(np.searchsorted(times_us, t_us, side="right") - 1, 0, len(times_us) - 2)
    span = (times_us[i + 1] - times_us[i]).astype(np.float64)
    w = np.where(span > 0, (t_us - times_us[i]) / np.where(span > 0, span, 1.0), 0.0)
    xy = poses[i, :2] + w[..., None] * (poses[i + 1, :2] - poses[i, :2])
    yaw = poses[i, 2] + w * wrap_angle(poses[i + 1, 2] - poses[i, 2])
    return np.concatenate([xy, wrap_angle(yaw)[..., None]], axis=-1)


def pose_clock_offset(T_prev_next: np.ndarray, inlier_ratio: np.ndarray, times_us: np.ndarray, poses: np.ndarray,
                      config: PoseClockConfig = PoseClockConfig(),
                      pose_at: Callable[[np.ndarray], np.ndarray] | None = None) -> PoseClockCheck:
    """The shift of the pose file's clock against the scans' (module docstring).

    Args:
        T_prev_next: (N-1, 3) registration of keyframe i+1 in keyframe i's frame (``consecutive_registrations``).
        inlier_ratio: (N-1,) each registration's aligned share.
        times_us: (N,) int64 keyframe times, increasing.
        poses: (N, 3) float64 ``T_map_keyframe`` from the pose file at those times.
        config: settings.
        pose_at: the pose file's pose at any keyframe time (µs (M,) -> (M, 3); e.g. at its mid-sweep time, as
            ``poses`` were taken; NaN rows where the file holds none: ``io.datasets.pose_file_reader``), to read it
            at shifted times; a pair counts as read wherever both its shifted times give a pose. None: ``poses``
            interpolated between keyframes (coarse where they lie seconds apart: a corner between two keyframes is
            cut), a pair counting where both shifted times stay inside the keyframes' span.

    Returns:
        ``PoseClockCheck``; ``offset_detected`` False (and ``offset_s`` 0) without enough registered pairs.
    """
    t = np.asarray(times_us, np.int64)
    P = np.asarray(poses, np.float64)
    meas = np.asarray(T_prev_next, np.float64)
    n = len(t)
    none = PoseClockCheck(0, float("nan"), 0.0, float("nan"), False)
    if n < 2 or meas.shape != (n - 1, 3) or np.any(np.diff(t) <= 0):
        return none
    gap_s = np.diff(t) / 1e6
    finite = np.isfinite(meas).all(axis=1)
    turning = np.degrees(np.abs(wrap_angle(np.where(finite, meas[:, 2], 0.0)))) >= config.min_turn_deg
    use = finite & turning & (np.asarray(inlier_ratio) >= config.min_inlier_ratio) & (gap_s <= config.max_pair_gap_s)
    if int(use.sum()) < config.min_pairs:
        return none
    a, b = t[:-1][use], t[1:][use]
    turn_meas = meas[use, 2]

    def read(at_us: np.ndarray) -> np.ndarray:
        """Poses at ``at_us``; NaN rows where none can be read: beyond the pose file (``pose_at``'s own NaN rows),
        or without ``pose_at`` beyond the keyframes' span."""
        if pose_at is not None:
            return np.asarray(pose_at(at_us), np.float64)
        out = _interpolate(t, P, at_us)
        out[(at_us < t[0]) | (at_us > t[-1])] = np.nan
        return out

    def pair_errors(offset_us: int) -> tuple[np.ndarray, np.ndarray]:
        """Each pair's disagreement (NaN where unread) with the poses read ``offset_us`` later, and where both its
        times could be read there."""
        pa, pb = read(a + offset_us), read(b + offset_us)
        inside = np.isfinite(pa).all(axis=1) & np.isfinite(pb).all(axis=1)
        rel = relative_pose(pa[inside], pb[inside])
        err = np.full(len(a), np.nan)
        err[inside] = np.minimum(np.degrees(np.abs(wrap_angle(rel[:, 2] - turn_meas[inside]))), config.clip_error_deg)
        return err, inside

    at_zero_each, readable = pair_errors(0)
    if not readable.all():  # pairs the pose reader holds no pose for as given (a reader narrower than the drive)
        a, b, turn_meas, at_zero_each = a[readable], b[readable], turn_meas[readable], at_zero_each[readable]
        if len(a) < config.min_pairs:
            return none
    at_zero = float(at_zero_each.mean())

    def error(offset_s: float) -> float:
        """Mean disagreement over every pair, each read at the shift where its shifted times can be read and as
        given where not: every shift judged on the same pairs, so that one which drops a badly registered pair off
        the drive's end does not look better for it (QA session 41: two turns 29 s apart, a pose file on the
        scans' clock refused as 29.2 s off; another 1 s off read as 28.25 s)."""
        shifted, inside = pair_errors(int(round(offset_s * 1e6)))
        if inside.mean() < config.min_coverage:
            return float("inf")
        return float(np.where(inside, shifted, at_zero_each).mean())

    coarse = np.arange(-config.max_offset_s, config.max_offset_s + 1e-9, config.coarse_step_s)
    errs = np.array([error(float(s)) for s in coarse])
    ties = np.flatnonzero(errs <= errs.min() + config.tie_deg)  # a periodic drive agrees at every period
    best = float(coarse[ties[np.argmin(np.abs(coarse[ties]))]])
    fine = np.arange(best - config.coarse_step_s, best + config.coarse_step_s + 1e-9, config.fine_step_s)
    fine_errs = np.array([error(float(s)) for s in fine])
    best, at_best = float(np.round(fine[int(np.argmin(fine_errs))], 6)), float(fine_errs.min())
    detected = bool(abs(best) >= config.min_offset_s and at_zero >= config.min_error_deg
                    and at_best <= config.max_error_ratio * at_zero)
    return PoseClockCheck(len(a), at_zero, best if detected else 0.0, at_best if detected else at_zero, detected)


def pose_clock_message(check: PoseClockCheck, what: str = "the poses") -> str:
    """What to tell a user whose pose file is off the scans' clock (``check.offset_detected``)."""
    off = check.offset_s
    return (f"{what} are {abs(off):.2f} s {'behind' if off < 0 else 'ahead of'} the scans' clock: the turns the scans "
            f"show between consecutive keyframes ({check.pairs} pairs) agree with the poses read {abs(off):.2f} s "
            f"{'earlier' if off < 0 else 'later'} (mean {check.error_at_offset_deg:.2f} deg) and not as given (mean "
            f"{check.error_at_zero_deg:.2f} deg), so every keyframe would carry another instant's pose. Put the pose "
            f"file on the scans' time base{gps_offset_hint(off)}: add "
            f"{-off:+.2f} s to its times")
