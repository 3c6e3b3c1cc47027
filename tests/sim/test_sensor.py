"""Sensor model: known targets, occlusion, motion distortion, format, determinism, weather."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from reradar_core.io.presets import get_preset
from reradar_core.sim.sensor import render_scan, scan_seed
from reradar_core.sim.traversal import Traversal
from reradar_core.sim.world import Primitives, World

from .conftest import CLEAN, T0, linear_trajectory


def _peak(scan, az_deg: float, range_m: float, az_win: int = 2, r_win_m: float = 0.8) -> float:
    row = int(round(np.radians(az_deg) / (2 * np.pi / scan.num_azimuths))) % scan.num_azimuths
    rows = [(row + k) % scan.num_azimuths for k in range(-az_win, az_win + 1)]
    b = int(round((range_m - scan.range_offset_m) / scan.range_resolution_m))
    w = int(r_win_m / scan.range_resolution_m)
    return float(scan.power[rows, b - w:b + w + 1].max())


def _empty_traversal(road, seed=1, condition="clear"):
    return Traversal(World(road, seed=0, profile="empty"), seed=seed, condition=condition, traffic_per_km=0.0)


def test_scan_format_matches_preset(road):
    trav = _empty_traversal(road)
    for name in ("oxford", "boreas"):
        p = get_preset(name)
        scan = render_scan(trav, linear_trajectory(), T0, p, 1, CLEAN)
        assert scan.power.shape == (400, p.num_range_bins)
        assert scan.power.dtype == np.float32 and 0 <= scan.power.min() and scan.power.max() <= 1
        assert scan.range_resolution_m == p.range_resolution_m
        # 400 azimuths over one 0.25 s sweep, timestamps from the sweep start
        assert scan.timestamp_us == T0
        assert np.all(np.diff(scan.timestamps_us) > 0)
        assert 249_000 <= scan.timestamps_us[-1] - T0 <= 250_000
        np.testing.assert_allclose(np.diff(scan.azimuths), 2 * np.pi / 400)
        # values are quantised to the 8-bit PNG levels
        np.testing.assert_allclose(scan.power * 255, np.round(scan.power * 255), atol=1e-4)


def test_occlusion_wall_hides_pole_open_pole_visible(road):
    """A pole directly behind a wall is not visible; the same pole in the open is."""
    trav = _empty_traversal(road)
    extra = Primitives()
    extra.add_segments(np.array([[20.0, -4.0, 20.0, 4.0]]), 2.0, 0.0, 0.5)  # opaque wall ahead
    extra.add_points(np.array([[30.0, 0.0], [0.0, -30.0]]), 4.0, 0)  # behind the wall / in the open (right)
    scan = render_scan(trav, linear_trajectory(), T0, "oxford", 7, CLEAN, extra=extra)
    # the same window over empty ground elsewhere: receiver noise + speckle only
    background = max(_peak(scan, az, 30.0) for az in (150, 180, 210, 240, 300))
    wall = _peak(scan, 0.0, 20.0)
    hidden = _peak(scan, 0.0, 30.0)
    visible = _peak(scan, 90.0, 30.0)  # azimuth is clockwise from +x: 90 deg = the vehicle's right
    assert wall > 0.3 and visible > 0.3
    assert background < 0.25
    assert hidden <= background
    # without the wall the hidden pole appears
    extra2 = Primitives()
    extra2.add_points(np.array([[30.0, 0.0]]), 4.0, 0)
    scan2 = render_scan(trav, linear_trajectory(), T0, "oxford", 7, CLEAN, extra=extra2)
    assert _peak(scan2, 0.0, 30.0) > 0.3


def test_vegetation_attenuates_but_does_not_block(road):
    trav = _empty_traversal(road)
    target = Primitives()
    target.add_points(np.array([[30.0, 0.0]]), 4.0, 0)
    hedge = Primitives()
    hedge.add_segments(np.array([[20.0, -4.0, 20.0, 4.0]]), 0.3, 0.35, 1.0)
    hedge.add_points(np.array([[30.0, 0.0]]), 4.0, 0)
    open_v = _peak(render_scan(trav, linear_trajectory(), T0, "oxford", 3, CLEAN, extra=target), 0, 30)
    veg_v = _peak(render_scan(trav, linear_trajectory(), T0, "oxford", 3, CLEAN, extra=hedge), 0, 30)
    background = 0.2
    assert background < veg_v < open_v


def _peak_position(scan, row_guess: int, range_guess_m: float) -> tuple[int, float]:
    """(row, range) of the brightest cell within +-3 rows / +-5 m of a guess (centroid along range)."""
    rows = np.arange(row_guess - 3, row_guess + 4) % scan.num_azimuths
    b0 = int((range_guess_m - 5.0) / scan.range_resolution_m)
    win = scan.power[rows, b0:b0 + int(10.0 / scan.range_resolution_m)]
    i, j = np.unravel_index(int(np.argmax(win)), win.shape)
    seg = win[i]
    sel = seg >= seg[j] - 0.03
    sel[: max(0, j - 20)] = False
    sel[j + 21:] = False
    centroid = float(np.sum(np.nonzero(sel)[0] * seg[sel]) / np.sum(seg[sel]))
    return int(rows[i]), scan.range_offset_m + (b0 + centroid) * scan.range_resolution_m


def test_motion_distortion_shifts_late_azimuths(road):
    """Each azimuth is measured from the pose at its own time. Driving at 10 m/s along +x, a pole at
    azimuth ~315 deg (front-left, measured ~0.22 s into the sweep) appears at the range from the pose of
    that moment (~1.5 m closer than in the static scan); a pole at ~45 deg (measured early) barely moves."""
    trav = _empty_traversal(road)
    cfg = replace(CLEAN, speckle_looks=0)  # no speckle: measure the geometry, not the noise
    poles = np.array([[28.28, 28.28], [28.28, -28.28]])  # 40 m at azimuth 315 deg and 45 deg
    extra = Primitives()
    extra.add_points(poles, 20.0, 0)
    static = render_scan(trav, linear_trajectory(speed_mps=0.0), T0, "oxford", 5, cfg, extra=extra)
    moving = render_scan(trav, linear_trajectory(speed_mps=10.0), T0, "oxford", 5, cfg, extra=extra)
    for (px, py), row_guess in zip(poles, (350, 50), strict=True):
        _, r_static = _peak_position(static, row_guess, 40.0)
        row, r_moving = _peak_position(moving, row_guess, 38.0)
        t = (moving.timestamps_us[row] - T0) / 1e6
        expected = float(np.hypot(px - 10.0 * t, py))
        assert abs(r_static - 40.0) < 0.15
        assert abs(r_moving - expected) < 0.15, (row, r_moving, expected)
    late_shift = _peak_position(moving, 350, 38.0)[1] - 40.0
    early_shift = _peak_position(moving, 50, 38.0)[1] - 40.0
    assert late_shift < -1.0 and abs(early_shift) < 0.5


def test_same_seed_same_scan_other_seed_other_noise(road):
    world = World(road, seed=4, profile="urban")
    trav = Traversal(world, seed=9)
    traj = linear_trajectory(x0=10.0, speed_mps=8.0)
    a = render_scan(trav, traj, T0, "boreas", scan_seed(9, 3))
    b = render_scan(Traversal(World(road, seed=4, profile="urban"), seed=9), traj, T0, "boreas", scan_seed(9, 3))
    c = render_scan(trav, traj, T0, "boreas", scan_seed(9, 4))
    np.testing.assert_array_equal(a.power, b.power)
    assert not np.array_equal(a.power, c.power)


def test_weather_adds_near_clutter_and_attenuates_but_leaves_receiver_floor(road):
    """Simulator v3: precipitation backscatter (volume clutter, within 60 m) brightens the near range, path
    attenuation dims far structure; the receiver noise floor far out (> 130 m, no returns) is unchanged."""
    from reradar_core.sim.traversal import get_condition

    world = World(road, seed=5, profile="urban")
    traj = linear_trajectory()
    near, floor, far = {}, {}, {}
    for cond in ("clear", "rain", "falling_snow"):
        for dry in (False, True):  # dry: the same condition without its precipitation clutter
            c = replace(get_condition(cond), volume_clutter_per_m2=0.0) if dry else get_condition(cond)
            s = render_scan(Traversal(world, seed=2, condition=c), traj, T0, "oxford", 11)
            r = s.ranges_m
            key = cond + ("-dry" if dry else "")
            near[key] = float(np.mean(s.power[:, (r > 5) & (r < 55)]))
            floor[key] = float(np.median(s.power[:, (r > 130)]))
            far[key] = float(np.percentile(s.power[:, (r > 60) & (r < 120)], 99.5))
    assert near["rain"] > near["rain-dry"] and near["falling_snow"] > near["falling_snow-dry"]
    assert near["clear"] == near["clear-dry"]
    assert abs(floor["rain"] - floor["clear"]) < 0.01 and abs(floor["falling_snow"] - floor["clear"]) < 0.01
    assert far["falling_snow"] < far["clear"]


def test_dominant_scatterer_flickers_less_than_fully_developed_speckle(road):
    """A pole (one dominant scatterer) keeps its mean power with Rician statistics but varies far less from
    scan to scan than under fully developed (exponential) speckle."""
    trav = _empty_traversal(road)
    extra = Primitives()
    extra.add_points(np.array([[0.0, -30.0]]), 4.0, 0)  # 30 m to the right
    cfg_full = replace(CLEAN, glint_db=0.0)
    cfg_dom = replace(cfg_full, dominant_fraction=1.0)
    vals = {}
    for name, cfg in (("full", cfg_full), ("dominant", cfg_dom)):
        vals[name] = np.array([_peak(render_scan(trav, linear_trajectory(), T0, "oxford", k, cfg, extra=extra),
                                     90.0, 30.0, az_win=0, r_win_m=0.1) for k in range(12)])
    assert vals["dominant"].std() < 0.5 * vals["full"].std()
    assert abs(np.median(vals["dominant"]) - np.median(vals["full"])) < 0.05


def test_render_scan_refuses_a_start_outside_the_drive_and_an_implicit_seed(road):
    """QA session 38: a start time in seconds rendered the whole sweep at the drive's first pose; scan_seed=None drew
    fresh noise on every call."""
    import pytest

    from reradar_core.errors import ConfigError

    trav, traj = _empty_traversal(road), linear_trajectory()
    with pytest.raises(ConfigError, match="outside the trajectory's times"):
        render_scan(trav, traj, T0 // 1_000_000, "oxford", 1, CLEAN)
    for seed in (None, -1, 1.5):
        with pytest.raises(ConfigError, match="scan_seed must be a non-negative int"):
            render_scan(trav, traj, T0, "oxford", seed, CLEAN)  # type: ignore[arg-type]
