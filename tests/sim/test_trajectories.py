"""Synthetic drives (``drive_route``): the corner speed cap (session 14's defect, docs/SIMULATOR.md "Known defect")."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reradar_core.sim.trajectories import _corner_speed_limit, drive_route

#: an L-shaped route: 300 m east, then 300 m north (one right-angle corner, rounded to ~8 m)
L_ROUTE = np.array([[0.0, 0.0], [300.0, 0.0], [300.0, 300.0]])


def _lateral_accel(traj, dt_s: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """(speed m/s, |speed x yaw rate| m/s^2) along ``traj`` sampled every ``dt_s`` (default 20 Hz)."""
    t = np.arange(traj.timestamps_us[0], traj.timestamps_us[-1], int(round(dt_s * 1e6)))
    p = traj.interpolate(t)
    v = np.hypot(*np.diff(p[:, :2], axis=0).T) / dt_s
    w = np.diff(np.unwrap(p[:, 2])) / dt_s
    return v, np.abs(v * w)


def test_default_corners_at_cruise_speed_and_the_cap_slows_down():
    fast = drive_route(L_ROUTE, seed=3, speed_mps=(10.0, 10.0))
    capped = drive_route(L_ROUTE, seed=3, speed_mps=(10.0, 10.0), max_lateral_accel_mps2=3.0)
    _, a_fast = _lateral_accel(fast)
    v_cap, a_cap = _lateral_accel(capped)
    assert a_fast.max() > 8.0  # v1-v8: the corner at 10 m/s
    assert a_cap.max() < 3.0 * 1.3  # within the curvature estimate's tolerance of the cap
    # straight stretches keep the cruise speed; the corner is slower; the path is the same
    assert np.isclose(np.median(v_cap), 10.0, atol=0.05) and v_cap.min() < 6.0
    assert np.allclose(capped.xy[-1], fast.xy[-1]) and capped.timestamps_us[-1] > fast.timestamps_us[-1]


def test_speed_limit_ramps_at_the_longitudinal_acceleration():
    """sqrt(a / curvature) at the corner, infinite-like on the straights, and v^2 changes by at most 2 a_long ds."""
    line = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 100.0]])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
    grid, vmax = _corner_speed_limit(line, s, lateral=3.0, longitudinal=2.0)
    assert vmax[np.argmin(np.abs(grid - 100.0))] < 3.0  # the unrounded kink: a very tight corner
    assert vmax[0] > 15.0 and vmax[-1] > 15.0
    assert np.all(np.abs(np.diff(vmax ** 2)) <= 2 * 2.0 * 0.5 + 1e-9)


def test_default_is_unchanged():
    a = drive_route(L_ROUTE, seed=5)
    b = drive_route(L_ROUTE, seed=5, max_lateral_accel_mps2=None)
    np.testing.assert_array_equal(a.timestamps_us, b.timestamps_us)
    np.testing.assert_array_equal(a.xy, b.xy)


def test_v9_every_synthetic_suite_corners_like_a_real_drive():
    """Simulator v9: every loop-route sequence of every suite (benchmarks, training splits, smoke, calibration),
    sampled at the radar's 4 Hz, corners below 1.2 x the 3.5 m/s^2 cap, as the real Boreas drives do (0.31-0.39 g
    on their rendered poses); v1-v8 reached 0.5-5.5 g on the same routes. The inner lane of a reversed, offset
    drive is capped too (the offset is driven, not added afterwards)."""
    from reradar_core.sim.suites import CORNER_LATERAL_ACCEL_MPS2, SUITES, _route_trajectory

    assert CORNER_LATERAL_ACCEL_MPS2 == 3.5
    checked = 0
    for suite in SUITES.values():
        for seq in suite.sequences:
            if seq.route.kind != "loop":
                continue
            assert seq.route.max_lateral_accel_mps2 == CORNER_LATERAL_ACCEL_MPS2, (suite.name, seq.name)
            _, a = _lateral_accel(_route_trajectory(seq.route, None), dt_s=0.25)  # the radar's 4 Hz
            assert a.max() < 1.2 * CORNER_LATERAL_ACCEL_MPS2, (suite.name, seq.name, a.max())
            checked += 1
    assert checked >= 25


def test_lateral_lane_is_the_offset_path_at_its_own_speeds():
    """``drive_route(lateral_m=d)`` drives the path ``offset_trajectory`` gives (same geometry), at the lane's own
    corner speeds. Shifting a centre-line drive keeps its yaw rate, so the outer lane of a corner (radius R + d) would
    corner at (R + d) / R times the centre line's lateral acceleration: over the cap on a tight corner."""
    from reradar_core.sim.trajectories import offset_trajectory

    left_turn = np.array([[0.0, 0.0], [300.0, 0.0], [300.0, 300.0]])  # east, then north: the right lane is outer
    centre = drive_route(left_turn, seed=3, speed_mps=(10.0, 10.0), max_lateral_accel_mps2=3.0)
    outer = drive_route(left_turn, seed=3, speed_mps=(10.0, 10.0), max_lateral_accel_mps2=3.0, lateral_m=-3.5)
    shifted = offset_trajectory(centre, -3.5)
    np.testing.assert_allclose(outer.xy[0], shifted.xy[0], atol=1e-6)
    np.testing.assert_allclose(outer.xy[-1], shifted.xy[-1], atol=1e-6)
    # the same path: every pose of the lane drive lies on the shifted drive's polyline (within 5 cm)
    seg_a, seg_b = shifted.xy[:-1], shifted.xy[1:]
    for q in outer.xy[::40]:
        ab = seg_b - seg_a
        u = np.clip(np.einsum("ij,ij->i", q - seg_a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12), 0, 1)
        assert np.min(np.linalg.norm(seg_a + u[:, None] * ab - q, axis=1)) < 0.05
    _, a_outer = _lateral_accel(outer)
    _, a_shifted = _lateral_accel(shifted)
    assert a_outer.max() < 3.0 * 1.3 < a_shifted.max()


def test_loop_grid_holds_every_street_the_loop_route_drives():
    """``synthetic_loop_grid`` gives the street grid ``synthetic_loop_route`` drives around (same seed): every
    waypoint lies on one of its north-south streets and one of its east-west streets."""
    from reradar_core.sim.trajectories import synthetic_loop_grid, synthetic_loop_route

    for seed in (11, 12, 500):
        xs, ys = synthetic_loop_grid(seed, block_m=(120.0, 200.0), n_blocks=3)
        wp = synthetic_loop_route(seed, block_m=(120.0, 200.0), n_blocks=3, laps=3)
        assert xs.shape == (4,) and ys.shape == (3,) and np.all(np.diff(xs) >= 120.0) and np.all(np.diff(ys) >= 120.0)
        assert np.all(np.min(np.abs(wp[:, :1] - xs[None, :]), axis=1) < 1e-9)
        assert np.all(np.min(np.abs(wp[:, 1:] - ys[None, :]), axis=1) < 1e-9)


def _csv(tmp_path, name: str, rows: list[tuple[float, float]]) -> Path:
    path = tmp_path / name
    path.write_text("t_s,x,y,yaw\n" + "".join(f"{t},{x},0,0\n" for t, x in rows))
    return path


def _sim(tmp_path, traj) -> object:
    from typer.testing import CliRunner

    from reradar_cli import app

    return CliRunner().invoke(app, ["sim", "--trajectory", str(traj), "--out", str(tmp_path / "out")])


def test_sim_refuses_negative_times_before_rendering(tmp_path):
    """QA 6: times from -5 s rendered radar/-5000000.png, which `reradar info` / `bench` then refused."""
    traj = _csv(tmp_path, "neg.csv", [(-5.0 + 0.25 * i, 2.0 * i) for i in range(40)])
    res = _sim(tmp_path, traj)
    assert res.exit_code == 2 and "neg.csv: the trajectory's times start at -5 s" in res.output
    assert "must not be negative: shift the times" in res.output
    assert not (tmp_path / "out").exists()


def test_sim_says_how_long_a_trajectory_must_be(tmp_path):
    """QA 13: one or two rows gave 'road network needs at least one polyline with two distinct points'."""
    for name, rows in (("one.csv", [(0.0, 0.0)]), ("two.csv", [(0.0, 0.0), (0.25, 1.25)]),
                       ("short.csv", [(0.0, 0.0), (10.0, 1.5)])):
        res = _sim(tmp_path, _csv(tmp_path, name, rows))
        assert res.exit_code == 2, res.output
        assert f"{name}: the trajectory has {len(rows)} pose(s)" in res.output
        assert "at least 2 poses spanning more than one radar sweep (0.25 s) and more than 2 m of path" in res.output
    from reradar_core.io.poses import read_poses
    from reradar_core.sim.trajectories import check_render_trajectory

    check_render_trajectory(read_poses(_csv(tmp_path, "ok.csv", [(0.0, 0.0), (0.5, 2.5)])), "ok.csv")


def test_sim_refuses_a_drive_whose_time_unit_makes_it_crawl_or_fly(tmp_path):
    """QA re-test (session 23): millisecond times read as seconds (--time-unit s) rendered a drive at 8 mm/s, and
    without --limit started 38,999 scans (an hour). A drive's mean speed must be a road vehicle's; the message names
    the unit that gives it one."""
    import pytest
    from typer.testing import CliRunner

    from reradar_cli import app
    from reradar_core.errors import ConfigError
    from reradar_core.io.poses import read_poses
    from reradar_core.sim.trajectories import check_render_trajectory

    ms = tmp_path / "ms.csv"  # 8 m/s for 10 s, times in milliseconds under a plain t header
    ms.write_text("t,x,y,yaw\n" + "".join(f"{250 * i},{2.0 * i},0,0\n" for i in range(41)))
    res = CliRunner().invoke(app, ["sim", "--trajectory", str(ms), "--time-unit", "s", "--out", str(tmp_path / "o")])
    assert res.exit_code == 2, res.output
    assert "80.0 m in 10000 s" in res.output and "pass --time-unit ms" in res.output
    assert not (tmp_path / "o").exists()
    with pytest.raises(ConfigError, match="probably in ms"):  # read as microseconds: 80 m in 10 ms
        check_render_trajectory(read_poses(ms, "us"), ms, "us")
    check_render_trajectory(read_poses(ms, "ms"), ms, "ms")  # 8 m/s
    # a vehicle that stands for minutes at the start of a short drive is no unit error
    stand = tmp_path / "stand.csv"
    stand.write_text("t_s,x,y,yaw\n0,0,0,0\n600,0,0,0\n" + "".join(f"{600 + i},{8.0 * i},0,0\n" for i in range(1, 6)))
    check_render_trajectory(read_poses(stand), stand)


def test_an_offset_past_the_centre_of_a_turn_is_refused():
    """A lane farther to the inside of a turn than the turn's radius would run backwards while its heading faces
    forwards (QA session 36: `sim --lateral 30` on a 25 m turn gave such ground truth, `--lateral 1e6` hung):
    refused, naming the radius; the outside of the turn and a lane inside the radius are driven."""
    import math

    import pytest

    from reradar_core.errors import ConfigError
    from reradar_core.io.poses import PoseSequence
    from reradar_core.sim.trajectories import offset_trajectory

    xy, yaw, x, y, h = [], [], 0.0, 0.0, 0.0
    for i in range(161):  # 8 m/s, a 90 deg left turn of radius 2 m / (pi / 40) = 25.5 m
        xy.append((x, y))
        yaw.append(h)
        if 60 <= i < 80:
            h += (math.pi / 2) / 20
        x, y = x + 2 * math.cos(h), y + 2 * math.sin(h)
    traj = PoseSequence(np.arange(161, dtype=np.int64) * 250_000, np.array(xy), np.array(yaw))
    for lateral in (30.0, 1e6):
        with pytest.raises(ConfigError, match=r"past the centre of its turn .*radius 25\.\d m"):
            offset_trajectory(traj, lateral)
    for lateral in (-30.0, 20.0, 3.5):  # the outside of the turn, and lanes inside its radius
        lane = offset_trajectory(traj, lateral)
        step = np.diff(lane.xy, axis=0)
        assert np.all(step[:, 0] * np.cos(lane.yaw[:-1]) + step[:, 1] * np.sin(lane.yaw[:-1]) > 0)


def test_heading_jitter_of_a_creeping_vehicle_is_no_turn():
    """A turn is judged over a metre of arc: a vehicle creeping at 0.8 m/s with 0.5 deg of heading jitter between
    10 Hz poses is offset by a lane without refusal (code review, session 36: refused as a 2.1 m turn)."""
    from reradar_core.io.poses import PoseSequence
    from reradar_core.sim.trajectories import offset_trajectory

    rng = np.random.default_rng(0)
    n = 600  # 48 m straight east
    xy = np.stack([np.arange(n) * 0.08, np.zeros(n)], axis=1)
    yaw = np.radians(rng.normal(0.0, 0.5, n))
    lane = offset_trajectory(PoseSequence(np.arange(n, dtype=np.int64) * 100_000, xy, yaw), 3.5)
    assert np.allclose(lane.xy[:, 1], 3.5, atol=0.1)
