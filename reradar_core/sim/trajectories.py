"""Trajectories for the simulator: real pose files, lateral offsets / time shifts, synthetic looped routes."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from reradar_core.errors import ConfigError, PoseFileError, ReRadarError
from reradar_core.geometry.se2 import wrap_angle
from reradar_core.io.poses import PoseSequence, read_poses
from reradar_core.sim.world import stable_seed

__all__ = [
    "load_trajectory",
    "load_road_xy",
    "check_render_trajectory",
    "offset_trajectory",
    "synthetic_loop_route",
    "drive_route",
    "synthetic_loop_grid",
    "scan_times",
]


def load_trajectory(path: str | Path, time_unit: str | None = None) -> PoseSequence:
    """Read any pose file ``read_poses`` understands (Boreas radar_poses.csv, MulRan, t,x,y,yaw CSV).

    Args:
        time_unit: unit of the file's timestamps (``s``, ``ms``, ``us``, ``ns``). None: absolute UTC times
            (unit from their magnitude) or the format's own unit (MulRan: ns); relative times without a unit
            raise ``PoseFileError`` saying what to pass (``reradar_core.io.poses``).

    Raises:
        PoseFileError: malformed file, ambiguous time unit, or fewer than two distinct times.
    """
    traj = read_poses(path, time_unit).sorted()
    if len(traj) >= 2 and np.any(np.diff(traj.timestamps_us) <= 0):
        raise PoseFileError(f"{path}: timestamps repeat after conversion to microseconds; is the time unit "
                            "right? (--time-unit s|ms|us|ns)")
    return traj


#: the road network resamples a trajectory every 2 m (``RoadNetwork``'s ``spacing_m``): a road needs more path
MIN_RENDER_PATH_M = 2.0
#: one radar sweep (``scan_times``' default): the first scan needs a whole sweep before the last pose, seconds
SWEEP_PERIOD_S = 0.25


#: a drive of at least this much path (metres) ...
PLAUSIBLE_SPEED_MIN_PATH_M = 20.0
#: ... whose mean speed lies outside this range (m/s) was read with a wrong time unit: a unit 1000x too coarse
#: turns 8 m/s into 8 mm/s (and a render of hours of 4 Hz scans), one 1000x too fine into 8 km/s
PLAUSIBLE_SPEED_M_S = (0.02, 150.0)


def _speed_unit_advice(span_us: float, length_m: float, time_unit: str | None) -> str:
    """Which time unit gives the drive a road vehicle's speed (10 m/s: ``length_m`` in ``length_m`` / 10 s), as
    advice."""
    from reradar_core.io.datasets import likely_time_unit
    from reradar_core.io.poses import TIME_UNITS

    likely = (likely_time_unit(span_us / TIME_UNITS[time_unit], length_m / 10.0 * 1e6)
              if time_unit in TIME_UNITS else None)
    if likely is None or likely == time_unit:
        return "check the time unit (--time-unit s|ms|us|ns, or a t_s / t_ms / t_us / t_ns header)"
    return f"the times are probably in {likely}: pass --time-unit {likely} (or name the column t_{likely})"


def check_render_trajectory(traj: PoseSequence, path: str | Path, time_unit: str | None = None) -> None:
    """Refuse a trajectory ``reradar sim`` cannot render, before the world is built.

    Args:
        traj: the trajectory (times in µs, positions in metres), sorted. path: its file, for the message.
        time_unit: the unit its times were read in (``--time-unit`` or its header; None: from the file), for the
            advice when the speed is implausible.

    Raises:
        ConfigError: negative times (scan files are named by their time in µs, which ``reradar info`` / ``bench``
            read as non-negative timestamps), fewer than 2 poses, a time span of one sweep
            (``SWEEP_PERIOD_S``) or less, a path of ``MIN_RENDER_PATH_M`` or less, or a drive of at least
            ``PLAUSIBLE_SPEED_MIN_PATH_M`` at a mean speed outside ``PLAUSIBLE_SPEED_M_S`` (a time unit 1000x off),
            or one step faster than sound (a position glitch, ``io.datasets.check_pose_steps``).
    """
    n = len(traj)
    if n and int(traj.timestamps_us[0]) < 0:
        raise ConfigError(f"{path}: the trajectory's times start at {traj.timestamps_us[0] / 1e6:g} s; scan files "
                          "are named by their time in µs, which must not be negative: shift the times to start at "
                          "0 or later (or give absolute UTC times)")
    span_s = (int(traj.timestamps_us[-1]) - int(traj.timestamps_us[0])) / 1e6 if n else 0.0
    length = traj.path_length_m() if n > 1 else 0.0
    lo, hi = PLAUSIBLE_SPEED_M_S  # first: a unit 1000x too fine also makes the drive too short
    if span_s > 0 and length >= PLAUSIBLE_SPEED_MIN_PATH_M and not lo <= length / span_s <= hi:
        raise ConfigError(f"{path}: the trajectory drives {length:.1f} m in {span_s:.6g} s, a mean speed of "
                          f"{length / span_s:.3g} m/s (a road vehicle drives {lo:g}-{hi:g} m/s): "
                          f"{_speed_unit_advice(span_s * 1e6, length, time_unit)}")
    from reradar_core.io.datasets import check_pose_steps

    try:  # after the mean: a whole file in another time unit gets the unit advice, a single glitch this
        check_pose_steps(traj, str(path))
    except ReRadarError as exc:
        raise ConfigError(str(exc)) from None
    if n < 2 or span_s <= SWEEP_PERIOD_S or length <= MIN_RENDER_PATH_M:
        raise ConfigError(f"{path}: the trajectory has {n} pose(s) over {span_s:g} s and {length:g} m; a render "
                          f"needs at least 2 poses spanning more than one radar sweep ({SWEEP_PERIOD_S:g} s) and "
                          f"more than {MIN_RENDER_PATH_M:g} m of path (the world's road is built along it)")


def load_road_xy(path: str | Path, time_unit: str | None = None) -> np.ndarray:
    """(N, 2) positions of a pose file used only as a road of the world (metres, in time order).

    A road needs no timing, so the file is read on its own terms first (absolute UTC times, the format's
    unit) and ``time_unit`` (the main trajectory's) is applied only where the file's times are ambiguous.
    """
    try:
        return load_trajectory(path).xy
    except PoseFileError:
        if time_unit is None:
            raise
        return load_trajectory(path, time_unit).xy


#: the centre line's path between the poses ``offset_trajectory`` compares (metres): a turn is judged over this much
#: arc, so the heading jitter of a vehicle creeping along (0.5 deg between 10 Hz poses 8 cm apart) is no turn
LANE_CHECK_ARC_M = 1.0


def _refuse_lane_past_turn_centre(traj: PoseSequence, lane_xy: np.ndarray, lateral_m: float) -> None:
    """Raise ``ConfigError`` where the lane ``lane_xy`` (the centre line ``traj`` shifted ``lateral_m`` to the left)
    does not move forwards over ``LANE_CHECK_ARC_M`` of the centre line's arc: at or past the centre of a turn, it
    stands or runs backwards while its heading faces forwards."""
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(traj.xy, axis=0), axis=1))])
    if arc[-1] < LANE_CHECK_ARC_M:
        return
    # one pose per LANE_CHECK_ARC_M of arc (the first at or after each mark)
    i = np.unique(np.searchsorted(arc, np.arange(0.0, arc[-1], LANE_CHECK_ARC_M)))
    i = i[i < len(traj)]
    yaw = traj.yaw[i]
    mid_yaw = yaw[:-1] + 0.5 * wrap_angle(np.diff(yaw))
    heading = np.stack([np.cos(mid_yaw), np.sin(mid_yaw)], axis=1)
    ahead = np.einsum("ij,ij->i", np.diff(traj.xy[i], axis=0), heading)  # metres driven forwards
    shifted = np.einsum("ij,ij->i", np.diff(lane_xy[i], axis=0), heading)
    bad = np.flatnonzero((ahead > 0.5 * LANE_CHECK_ARC_M) & (shifted <= 0.0))
    if bad.size == 0:
        return
    k = int(bad[np.argmin(shifted[bad] / ahead[bad])])
    turn = abs(float(wrap_angle(yaw[k + 1] - yaw[k])))
    radius = ahead[k] / turn if turn > 0 else math.inf
    t_s = (int(traj.timestamps_us[i[k]]) - int(traj.timestamps_us[0])) / 1e6
    raise ConfigError(
        f"a lane {abs(lateral_m):g} m to the {'left' if lateral_m > 0 else 'right'} of the trajectory reaches past the "
        f"centre of its turn at {t_s:.2f} s (radius {radius:.1f} m): that lane would stand or run backwards while facing "
        "forwards; give an offset smaller than the trajectory's tightest turn radius (a lane is ~3.5 m)")


def offset_trajectory(traj: PoseSequence, lateral_m: float = 0.0, time_shift_us: int = 0) -> PoseSequence:
    """The same drive shifted ``lateral_m`` to the vehicle's left (another lane) and in time.

    Raises:
        ConfigError: the offset reaches past the centre of a turn (``lateral_m`` at least the turn's radius, on its
            inside): the shifted lane would run backwards while its heading still points forwards, a drive no
            vehicle makes, and its ground truth would be wrong.
    """
    n = np.stack([-np.sin(traj.yaw), np.cos(traj.yaw)], axis=1)
    xy = traj.xy + lateral_m * n
    if lateral_m and len(traj) > 1:
        _refuse_lane_past_turn_centre(traj, xy, lateral_m)
    return PoseSequence(traj.timestamps_us + int(time_shift_us), xy, traj.yaw)


def drive_route(waypoints: np.ndarray, seed: int, start_time_us: int = 1_600_000_000_000_000,
                speed_mps: tuple[float, float] = (6.0, 12.0), rate_hz: float = 20.0,
                corner_radius_m: float = 8.0, max_lateral_accel_mps2: float | None = None,
                max_longitudinal_accel_mps2: float = 2.0, lateral_m: float = 0.0) -> PoseSequence:
    """Drive along a waypoint polyline with rounded corners and a smoothly varying speed (plus short stops).

    Args:
        waypoints: (N, 2) metres.
        seed: speed profile seed.
        start_time_us: time of the first pose.
        speed_mps: range of cruise speeds.
        rate_hz: pose rate of the output.
        corner_radius_m: corner rounding (Chaikin cuts), metres.
        max_lateral_accel_mps2: None (simulator v1-v8): the speed ignores the path's curvature, so corners are taken
            at cruise speed (up to 2.7 g on the loop routes; docs/SIMULATOR.md, "Known defect"; the suites'
            routes use 3.5 since simulator v9). A value caps the
            speed at sqrt(a / curvature) (``_corner_speed_limit``), reached and left at
            ``max_longitudinal_accel_mps2`` (braking before the corner, accelerating after it); urban drivers
            corner at 2-4 m/s^2.
        max_longitudinal_accel_mps2: braking / acceleration into and out of a corner (with
            ``max_lateral_accel_mps2``), m/s^2.
        lateral_m: drive a lane this far to the left of the (rounded) waypoint path, metres. The lane is offset
            before the speed profile is made, so the corner cap holds on the inner lane of a corner (whose radius is
            smaller by ``lateral_m``); ``offset_trajectory`` of a centre-line drive is the same path at the centre
            line's speeds.

    Returns:
        PoseSequence with yaw along the direction of travel.
    """
    wp = np.asarray(waypoints, dtype=np.float64)
    if len(wp) < 2:
        raise ConfigError("a route needs at least two waypoints")
    # corner cutting
    line = wp
    for _ in range(4):
        a, b = line[:-1], line[1:]
        seg = np.linalg.norm(b - a, axis=1, keepdims=True)
        frac = np.minimum(0.25, corner_radius_m / np.maximum(seg, 1e-9) / 2)
        q = a + frac * (b - a)
        r = b - frac * (b - a)
        line = np.concatenate([line[:1], np.stack([q, r], axis=1).reshape(-1, 2), line[-1:]])
    if lateral_m:
        line = _offset_polyline(line, lateral_m)
    d = np.linalg.norm(np.diff(line, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(d)])
    rng = np.random.default_rng(stable_seed(seed, "speed"))
    # speed: smooth random profile over arc length; slow down in curves; occasional stops
    knots = np.arange(0, s[-1] + 100, 100.0)
    v_knots = rng.uniform(*speed_mps, len(knots))
    dt = 1.0 / rate_hz
    corner_v = _corner_speed_limit(line, s, max_lateral_accel_mps2, max_longitudinal_accel_mps2) \
        if max_lateral_accel_mps2 is not None else None
    t_list, s_list = [0.0], [0.0]
    stops = set(np.nonzero(rng.random(len(knots)) < 0.08)[0].tolist())
    cur_s, cur_t, last_knot = 0.0, 0.0, 0
    while cur_s < s[-1]:
        k = int(cur_s // 100.0)
        if k in stops and k != last_knot:
            last_knot = k
            for _ in range(int(rng.uniform(2, 6) / dt)):  # a 2-6 s stop
                cur_t += dt
                t_list.append(cur_t)
                s_list.append(cur_s)
        v = float(np.interp(cur_s, knots, v_knots))
        if corner_v is not None:
            v = min(v, float(np.interp(cur_s, *corner_v)))
        cur_s = min(s[-1], cur_s + v * dt)
        cur_t += dt
        t_list.append(cur_t)
        s_list.append(cur_s)
    t = np.asarray(t_list)
    sa = np.asarray(s_list)
    x = np.interp(sa, s, line[:, 0])
    y = np.interp(sa, s, line[:, 1])
    # heading from the path tangent at each arc position (stable while stopped)
    yaw = _tangent_heading(line, s, sa, 0.5)
    return PoseSequence(start_time_us + np.round(t * 1e6).astype(np.int64), np.column_stack([x, y]), yaw)


def _offset_polyline(line: np.ndarray, lateral_m: float) -> np.ndarray:
    """(N, 2) polyline moved ``lateral_m`` to the left of its direction of travel, vertex by vertex along the
    normal of the mean of the adjacent segment directions (the rounded corners keep the offset path smooth)."""
    seg = np.diff(line, axis=0)
    seg /= np.maximum(np.linalg.norm(seg, axis=1, keepdims=True), 1e-12)
    tangent = np.concatenate([seg[:1], seg[:-1] + seg[1:], seg[-1:]])
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    return line + lateral_m * np.column_stack([-tangent[:, 1], tangent[:, 0]])


def _tangent_heading(line: np.ndarray, s: np.ndarray, at: np.ndarray, eps_m: float) -> np.ndarray:
    """Heading (rad) of the polyline ``line`` (N, 2), arc lengths ``s`` (N,), at arc positions ``at``: the chord
    from ``at - eps_m`` to ``at + eps_m`` (clipped to the path's ends)."""
    lo, hi = np.maximum(at - eps_m, 0), np.minimum(at + eps_m, s[-1])
    return np.arctan2(np.interp(hi, s, line[:, 1]) - np.interp(lo, s, line[:, 1]),
                      np.interp(hi, s, line[:, 0]) - np.interp(lo, s, line[:, 0]))


def _corner_speed_limit(line: np.ndarray, s: np.ndarray, lateral: float, longitudinal: float,
                        step_m: float = 0.5, half_window_m: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(arc positions (M,), speed limits (M,) m/s) along the polyline ``line`` (N, 2) with arc lengths ``s`` (N,):
    sqrt(lateral / curvature), curvature = heading change over +-``half_window_m`` of path / its length, its
    largest value within +-2 m (a rounded polyline corner's curvature sits at its vertices), then limited so that
    the speed changes by at most ``longitudinal`` m/s^2 along the path (v^2 <= v'^2 + 2 a ds)."""
    grid = np.arange(0.0, s[-1] + step_m, step_m)
    a, b = np.maximum(grid - half_window_m, 0.0), np.minimum(grid + half_window_m, s[-1])
    turn = np.abs(np.angle(np.exp(1j * (_tangent_heading(line, s, b, 0.25) - _tangent_heading(line, s, a, 0.25)))))
    curvature = turn / np.maximum(b - a, 1e-9)
    reach = int(round(2.0 / step_m))
    padded = np.pad(curvature, reach, mode="edge")
    curvature = np.lib.stride_tricks.sliding_window_view(padded, 2 * reach + 1).max(axis=1)
    v2 = lateral / np.maximum(curvature, 1e-9)  # squared speed limit
    ds2 = 2.0 * longitudinal * step_m
    for i in range(len(v2) - 2, -1, -1):  # brake before a corner
        v2[i] = min(v2[i], v2[i + 1] + ds2)
    for i in range(1, len(v2)):  # accelerate out of it
        v2[i] = min(v2[i], v2[i - 1] + ds2)
    return grid, np.sqrt(v2)


def synthetic_loop_grid(seed: int, block_m: tuple[float, float] = (70.0, 140.0), n_blocks: int = 3,
                        origin: tuple[float, float] = (0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """The street grid ``synthetic_loop_route`` drives around (same seed, blocks and origin): the x of its
    north-south streets, (n_blocks + 1,), and the y of its east-west streets, (3,), metres."""
    return _loop_grid_lines(np.random.default_rng(stable_seed(seed, "route")), block_m, n_blocks, origin)


def _loop_grid_lines(rng: np.random.Generator, block_m: tuple[float, float], n_blocks: int,
                     origin: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    widths = rng.uniform(*block_m, n_blocks)
    heights = rng.uniform(*block_m, 2)
    return (np.concatenate([[0.0], np.cumsum(widths)]) + origin[0],
            np.concatenate([[0.0], np.cumsum(heights)]) + origin[1])


def synthetic_loop_route(seed: int, block_m: tuple[float, float] = (70.0, 140.0), n_blocks: int = 3,
                         laps: int = 2, origin: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Waypoints of a route around a small street grid that is driven ``laps`` times (revisits for the
    single-session protocol): a rectangular circuit with an inner cross street taken on alternate laps.

    Returns:
        (N, 2) waypoints, metres.
    """
    rng = np.random.default_rng(stable_seed(seed, "route"))
    xs, ys = _loop_grid_lines(rng, block_m, n_blocks, origin)
    outer = [(xs[0], ys[0]), (xs[-1], ys[0]), (xs[-1], ys[-1]), (xs[0], ys[-1])]
    pts: list[tuple[float, float]] = []
    for lap in range(laps):
        if lap % 2 == 0:
            pts += outer
        else:
            # figure-eight-ish: go along the middle street, then around
            k = int(rng.integers(1, n_blocks))
            pts += [(xs[0], ys[0]), (xs[k], ys[0]), (xs[k], ys[1]), (xs[-1], ys[1]), (xs[-1], ys[-1]),
                    (xs[0], ys[-1])]
    pts.append(pts[0])
    return np.asarray(pts, dtype=np.float64)


def scan_times(traj: PoseSequence, sweep_period_s: float = 0.25, every: int = 1, limit: int | None = None,
               use_pose_times: bool | None = None) -> np.ndarray:
    """Scan start times (first azimuth), microseconds.

    With ``use_pose_times`` the pose timestamps themselves are the scan times (real radar pose files hold one
    pose per scan); otherwise scans tile the trajectory's time span at the sweep period. ``None`` decides by
    the pose rate: pose files at the sweep rate (median interval within 20 % of the period) use their times.
    Every ``every``-th scan is kept, at most ``limit`` of them; a full sweep must fit before the last pose.
    """
    if every < 1:
        raise ConfigError(f"every must be >= 1, got {every}")
    t = traj.timestamps_us
    period = int(round(sweep_period_s * 1e6))
    if use_pose_times is None:
        dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
        use_pose_times = abs(dt - period) <= 0.2 * period
    if use_pose_times:
        times = t[t + period <= t[-1]]
    else:
        times = np.arange(t[0], t[-1] - period, period, dtype=np.int64)
    times = times[::every]
    if limit is not None:
        times = times[:limit]
    return times
