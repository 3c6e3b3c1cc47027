"""The pose-clock check: a pose file read at other times than the scans' is found by the turns between consecutive
keyframes (known answers on constructed drives)."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.geometry.se2 import relative_pose
from reradar_core.localization.pose_clock import PoseClockConfig, pose_clock_message, pose_clock_offset


def _drive(kind: str, hz: float = 4.0, seconds: float = 120.0) -> tuple[np.ndarray, callable]:
    """Keyframe times (µs) and the drive's true pose at any time (µs -> (3,)): 10 m/s with six turns of 45-135
    degrees at irregular times (``corners``), straight at 10 m/s (``straight``) or a slalom of +-15 degrees with a
    12 s period (``slalom``)."""
    t_us = (1_600_000_000_000_000 + np.arange(0, seconds, 1 / hz) * 1e6).astype(np.int64)
    t0 = t_us[0]

    turns = [(12.0, 90.0, 4.0), (31.0, -90.0, 3.0), (47.0, 45.0, 5.0), (70.0, 90.0, 4.0), (88.0, -135.0, 6.0),
             (104.0, 90.0, 3.5)]  # (start s, angle deg, duration s): no period a shift could repeat

    def yaw_at(s: np.ndarray) -> np.ndarray:
        if kind == "straight":
            return np.zeros_like(s)
        if kind == "slalom":  # the same turns every 12 s
            return np.radians(15.0) * np.sin(2 * np.pi * s / 12.0)
        return sum(np.radians(a) * np.clip((s - t) / d, 0.0, 1.0) for t, a, d in turns)

    def pose_at(t: np.ndarray) -> np.ndarray:
        s = (np.asarray(t, np.float64) - t0) / 1e6
        fine = np.linspace(-60.0, seconds + 60.0, 40_001)  # integrate the heading: x, y along the drive
        yaw = yaw_at(fine)
        dx = np.cumsum(10.0 * np.cos(yaw)) * (fine[1] - fine[0])
        dy = np.cumsum(10.0 * np.sin(yaw)) * (fine[1] - fine[0])
        return np.stack([np.interp(s, fine, dx), np.interp(s, fine, dy), np.interp(s, fine, yaw)], axis=-1)

    return t_us, pose_at


def _measured(t_us: np.ndarray, pose_at: callable, noise_deg: float = 0.3, seed: int = 0) -> np.ndarray:
    """Registrations of keyframe i+1 in keyframe i's frame: the true relative poses with heading noise."""
    true = pose_at(t_us)
    rel = relative_pose(true[:-1], true[1:])
    rel[:, 2] += np.radians(np.random.default_rng(seed).normal(0.0, noise_deg, len(rel)))
    return rel


@pytest.mark.parametrize("offset_s", [-18.0, -1.0, -0.5, 0.5, 1.0, 2.0])
def test_poses_read_at_other_times_are_found_with_their_offset(offset_s: float) -> None:
    t_us, pose_at = _drive("corners")
    meas = _measured(t_us, pose_at)
    given = pose_at(t_us + int(offset_s * 1e6))  # a pose file whose times are offset_s behind the scans' clock
    check = pose_clock_offset(meas, np.ones(len(meas)), t_us, given)
    assert check.offset_detected
    assert check.offset_s == pytest.approx(-offset_s, abs=0.05)  # read the poses that much earlier to agree
    assert check.error_at_offset_deg < 0.5 * check.error_at_zero_deg
    assert check.pairs == int((np.degrees(np.abs(meas[:, 2])) >= 1.0).sum())  # the turning pairs only
    text = pose_clock_message(check)
    assert f"{abs(offset_s):.2f} s {'behind' if offset_s > 0 else 'ahead of'} the scans' clock" in text
    assert f"add {offset_s:+.2f} s to its times" in text  # what makes the file agree


def test_poses_on_the_scans_clock_or_within_a_sweep_pass() -> None:
    t_us, pose_at = _drive("corners")
    meas = _measured(t_us, pose_at)
    for offset_s in (0.0, 0.1, -0.2):
        check = pose_clock_offset(meas, np.ones(len(meas)), t_us, pose_at(t_us + int(offset_s * 1e6)))
        assert not check.offset_detected and check.offset_s == 0.0, (offset_s, check)


def test_a_drive_without_turns_or_without_registrations_gives_no_verdict() -> None:
    t_us, pose_at = _drive("straight")
    meas = _measured(t_us, pose_at)
    check = pose_clock_offset(meas, np.ones(len(meas)), t_us, pose_at(t_us + 1_000_000))
    assert not check.offset_detected  # steady speed, no turn: nothing tells the clocks apart
    t_us, pose_at = _drive("corners")
    meas = _measured(t_us, pose_at)
    given = pose_at(t_us + 1_000_000)
    weak = np.full(len(meas), 0.2)  # registrations below the answers' floor do not count
    assert pose_clock_offset(meas, weak, t_us, given).pairs == 0
    failed = meas.copy()
    failed[:] = np.nan
    assert not pose_clock_offset(failed, np.ones(len(meas)), t_us, given).offset_detected
    few = PoseClockConfig(min_pairs=len(meas) + 1)
    assert not pose_clock_offset(meas, np.ones(len(meas)), t_us, given, few).offset_detected


def test_pairs_across_a_recording_gap_are_left_out() -> None:
    t_us, pose_at = _drive("corners")
    t_gap = t_us.copy()
    t_gap[200:] += 10_000_000  # 10 s missing: the pair across it is no drive between two sweeps
    meas = _measured(t_us, pose_at)
    check = pose_clock_offset(meas, np.ones(len(meas)), t_gap, pose_at(t_us))
    assert check.pairs == int((np.degrees(np.abs(meas[:, 2])) >= 1.0).sum()) - 1  # and not the one across it


def test_config_is_checked() -> None:
    with pytest.raises(ValueError, match="min_inlier_ratio"):
        PoseClockConfig(min_inlier_ratio=0.0)
    with pytest.raises(ValueError, match="max_offset_s"):
        PoseClockConfig(max_offset_s=-1.0)


def test_a_drive_that_repeats_its_turns_is_read_at_the_smallest_agreeing_shift() -> None:
    """A slalom agrees with itself a period (12 s) away: the check found a pose file 1 s off at 11 s before ties
    were broken toward the smallest shift (session 41); an offset beyond half a period is still refused, by its
    alias (-6 s for 18 s), which is the most a drive that repeats itself can tell."""
    t_us, pose_at = _drive("slalom", seconds=90.0)
    meas = _measured(t_us, pose_at, noise_deg=0.05)
    for offset_s, found in ((1.0, -1.0), (-2.0, 2.0), (18.0, -6.0)):
        check = pose_clock_offset(meas, np.ones(len(meas)), t_us, pose_at(t_us + int(offset_s * 1e6)))
        assert check.offset_detected and check.offset_s == pytest.approx(found, abs=0.05), (offset_s, check)
    with pytest.raises(ValueError, match="tie_deg"):
        PoseClockConfig(tie_deg=0.0)


def test_a_shift_is_judged_on_every_pair_not_only_those_it_keeps_inside_the_drive() -> None:
    """QA session 41: a 46 s drive with two right-angle turns 29 s apart and one badly registered pair. Scored on the
    pairs a shift keeps inside the drive, 29 s dropped the bad pair and looked better than 0: a pose file on the
    scans' clock was refused as 29.2 s off, and one 1 s off was read as 28.25 s. A pair the shift takes beyond the
    drive now counts as given."""
    t_us = (1_600_000_000_000_000 + np.arange(0, 46, 0.75) * 1e6).astype(np.int64)
    t0 = t_us[0]

    def pose_at(t: np.ndarray) -> np.ndarray:
        s = (np.asarray(t, np.float64) - t0) / 1e6
        fine = np.linspace(-40.0, 90.0, 26_001)
        yaw = sum(np.radians(90.0) * np.clip((fine - c) / 4.0, 0.0, 1.0) for c in (8.0, 37.0))
        dx, dy = (np.cumsum(10.0 * f(yaw)) * (fine[1] - fine[0]) for f in (np.cos, np.sin))
        return np.stack([np.interp(s, fine, dx), np.interp(s, fine, dy), np.interp(s, fine, yaw)], axis=-1)

    meas = _measured(t_us, pose_at, noise_deg=0.3)
    late = int(np.flatnonzero(np.degrees(np.abs(meas[:, 2])) >= 1.0)[-2])  # a pair of the second turn
    meas[late, 2] += np.radians(8.0)  # registered wrong
    ones = np.ones(len(meas))
    check = pose_clock_offset(meas, ones, t_us, pose_at(t_us), pose_at=pose_at)
    assert not check.offset_detected, check
    # +-18 s (GPS against UTC time): read where the pose file covers, not only inside the 46 s of scans (QA s41)
    for offset_s in (1.0, -1.0, 18.0, -18.0):
        def shifted(t: np.ndarray, d: int = int(offset_s * 1e6)) -> np.ndarray:
            return pose_at(np.asarray(t) + d)

        check = pose_clock_offset(meas, ones, t_us, shifted(t_us), pose_at=shifted)
        assert check.offset_detected and check.offset_s == pytest.approx(-offset_s, abs=0.051), (offset_s, check)


def test_a_pose_reader_gives_no_pose_beyond_its_file_and_those_shifts_are_not_scored() -> None:
    """``io.datasets.pose_file_reader``: NaN beyond the pose file (past its slack), so a shift that reads there counts
    those pairs as given; a file that covers the shifted times is read there."""
    from reradar_core.io.datasets import pose_file_reader
    from reradar_core.io.poses import PoseSequence
    from reradar_core.io.presets import get_preset

    t_us, pose_at = _drive("corners")
    rows = t_us[::2]
    track = PoseSequence(rows, pose_at(rows)[:, :2], pose_at(rows)[:, 2])
    read = pose_file_reader(track, get_preset("boreas"))
    inside = read(t_us[:3])
    assert np.isfinite(inside).all()
    beyond = read(np.array([t_us[0] - 2_000_000, t_us[-1] + 2_000_000]))  # 2 s: past the 0.5 s slack + a sweep
    assert np.isnan(beyond).all()
    meas = _measured(t_us, pose_at)
    check = pose_clock_offset(meas, np.ones(len(meas)), t_us, read(t_us), pose_at=read)
    assert not check.offset_detected  # on the scans' clock
