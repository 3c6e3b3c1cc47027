"""Simulator v5 options (issue 10, hard suites): multi-lane traffic, repeated tile layouts, vehicle attitude,
per-suite profile / sensor overrides. Each defaults to v4 behaviour; known answers on small synthetic worlds."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from reradar_core.sim.sensor import SensorConfig, _ground_peaks, attitude, render_scan, scan_seed
from reradar_core.sim.suites import SUITES, suite_profile
from reradar_core.sim.traversal import Traversal
from reradar_core.sim.world import ELEV_VEHICLE, PROFILES, Primitives, World

from .conftest import CLEAN, T0, linear_trajectory, straight_road


def test_traffic_lanes_default_is_v4_and_lanes_sit_beside_the_median():
    world = World(straight_road(3000.0), seed=0, profile="empty")
    v4 = Traversal(world, seed=5, traffic_per_km=30.0)
    same = Traversal(world, seed=5, traffic_per_km=30.0, traffic_lanes=None)
    np.testing.assert_array_equal(v4._veh_lane, same._veh_lane)
    np.testing.assert_array_equal(np.abs(v4._veh_lane), 0.4 * world.profile.road_half_width_m)
    multi = Traversal(world, seed=5, traffic_per_km=30.0, traffic_lanes=3, median_m=2.0)
    # the other draws (positions, speeds, sizes) are those of the default traffic
    np.testing.assert_array_equal(multi._veh_idx0, v4._veh_idx0)
    np.testing.assert_array_equal(multi._veh_speed, v4._veh_speed)
    np.testing.assert_array_equal(np.sign(multi._veh_lane), np.sign(v4._veh_lane))
    # lane centres 1 + 1.75, 1 + 5.25, 1 + 8.75 m off the centreline; all three used
    assert set(np.round(np.abs(multi._veh_lane), 6)) == {2.75, 6.25, 9.75}


def test_tile_types_repeat_the_road_independent_layout():
    road = straight_road(400.0)  # along y = 0: tiles with iy = 3 (120-160 m) hold no road
    base = PROFILES["urban"]
    assert base.tile_types == 0
    v4 = World(road, seed=1, profile=base)
    rep = World(road, seed=1, profile=replace(base, tile_types=1))  # one type: every tile alike
    a, b = rep.tile(0, 3), rep.tile(2, 3)
    np.testing.assert_allclose(a.pts - [0.0, 0.0], b.pts - [80.0, 0.0])  # same layout, shifted by the tile
    assert len(a.pts) > 50
    c, d = v4.tile(0, 3), v4.tile(2, 3)
    assert not (c.pts.shape == d.pts.shape and np.allclose(c.pts, d.pts - [80.0, 0.0]))
    # default profile: the same tiles as a world built before the option existed (same seeds)
    np.testing.assert_array_equal(World(road, seed=1, profile="urban").tile(0, 3).pts, c.pts)


def test_attitude_moves_the_ground_peak_and_defaults_to_level():
    cfg = SensorConfig()
    assert cfg.attitude_deg == 0.0 and attitude(7, 12.3, cfg) == (0.0, 0.0)
    th = np.radians([0.0, 90.0, 180.0, 270.0])
    np.testing.assert_allclose(_ground_peaks(th, 0.0, 0.0, cfg), cfg.ground_peak_m)
    # nose 1 deg down: the beam meets the ground nearer ahead (2 / tan(2.86 + 1 deg) = 29.7 m), farther behind
    pk = _ground_peaks(th, np.radians(1.0), 0.0, cfg)
    np.testing.assert_allclose(pk, [29.66, 40.0, 61.6, 40.0], rtol=0.01)
    # smooth, zero-mean, std ~ attitude_deg over a long drive; other traversal -> other attitude
    c2 = replace(cfg, attitude_deg=2.0)
    ts = np.arange(0.0, 3000.0, 0.5)
    p = np.degrees([attitude(7, t, c2)[0] for t in ts])
    assert abs(p.mean()) < 0.3 and 1.5 < p.std() < 2.5
    q = np.degrees([attitude(7, t + 0.05, c2)[0] for t in ts])
    assert np.abs(q - p).max() < 1.0  # smooth: < 1 deg in 50 ms
    assert attitude(8, 100.0, c2) != attitude(7, 100.0, c2)


def test_attitude_changes_the_ground_only_with_the_option(road):
    world = World(road, seed=4, profile="urban")
    traj = linear_trajectory(x0=10.0, speed_mps=8.0)
    a = render_scan(Traversal(world, seed=9), traj, T0, "boreas", scan_seed(9, 3), CLEAN)
    b = render_scan(Traversal(world, seed=9), traj, T0, "boreas", scan_seed(9, 3), replace(CLEAN, attitude_deg=0.0))
    np.testing.assert_array_equal(a.power, b.power)
    c = render_scan(Traversal(world, seed=9), traj, T0, "boreas", scan_seed(9, 3), replace(CLEAN, attitude_deg=3.0))
    assert not np.array_equal(a.power, c.power)


def test_only_the_kaist_oord_and_boreas_worlds_differ_from_v4():
    """Simulator v5 adopted one override (docs/SIMULATOR.md, "Simulator v5"): ``loop-sim`` and its training split
    ``train-target-loop`` (same world, seed 11) render the ``urban`` profile with a continuous facade on 40 % of the
    tile sides instead of 80 %. Simulator v6 another ("Simulator v6"): the off-road suites and their training split
    vary their land use along the route (``zone_contrast`` 0.8). Simulator v7 a third ("Simulator v7"): the Boreas
    suite and its training split run on 16 m arterials (``road_half_width_m`` 8, the ``suburban`` profile: 6).
    Every other suite keeps v4's world, traffic and sensor (byte-identical renders); for them ``suite_profile`` is
    the profile itself. (Simulator v8 changes no world: it lets the beam pass over cars on the MulRan suites, as
    v4 did on the Boreas ones; ``test_world.py``. Simulator v11 adds open moor to ``offroad-sim-hard`` alone.)"""
    # (session 25: a training split's look-alike suite renders the split's profile in a world of another seed)
    kaist = {"loop-sim", "train-target-loop", "train-target-loop-lookalike"}
    oord = {"offroad-sim", "offroad-sim-hard", "train-target-offroad", "train-target-offroad-lookalike"}
    boreas = {"boreas-sim", "train-target-boreas", "train-target-boreas-lookalike"}
    for name, s in SUITES.items():
        assert s.sensor_overrides == (), name
        if name.endswith("-periodic"):  # session 26: the split's own overrides, then one tile layout everywhere
            split = SUITES[name.removesuffix("-periodic")]
            assert s.profile_overrides == split.profile_overrides + (("tile_types", 1),), name
            assert suite_profile(s) == replace(suite_profile(split), tile_types=1)
            continue
        assert s.traffic_lanes is None and s.median_m == 0.0 and s.ego_clearance_m is None, name
        if name in kaist:
            assert s.profile_overrides == (("frontage_prob", 0.4),), name
            prof = suite_profile(s)
            assert prof.name == "urban" and prof.frontage_prob == 0.4
            assert prof.frontage_prob != PROFILES["urban"].frontage_prob
            assert replace(prof, frontage_prob=PROFILES["urban"].frontage_prob) == PROFILES["urban"]
        elif name in oord:
            # simulator v11: the Two Lochs-like suite alone adds flat open moor with clutter drawn per drive
            moor = (("open_share", 0.2), ("open_scale_m", 600.0), ("open_clutter_persistence", 0.0))
            assert s.profile_overrides == (("zone_contrast", 0.8),) + (moor if name == "offroad-sim-hard" else ()), name
            prof = suite_profile(s)
            assert prof.name == "offroad" and prof.zone_contrast == 0.8 and PROFILES["offroad"].zone_contrast == 0.0
            assert (prof.open_share, prof.open_clutter_persistence) == ((0.2, 0.0) if name == "offroad-sim-hard"
                                                                        else (0.0, 1.0))
        elif name in boreas:
            assert s.profile_overrides == (("road_half_width_m", 8.0),), name
            prof = suite_profile(s)
            assert prof.name == "suburban" and PROFILES["suburban"].road_half_width_m == 6.0
            assert replace(prof, road_half_width_m=6.0) == PROFILES["suburban"]
        else:
            assert s.profile_overrides == (), name
            if s.profile != "mixed":
                assert suite_profile(s) is PROFILES[s.profile]
    assert SUITES["loop-sim"].world_seed == SUITES["train-target-loop"].world_seed
    assert SUITES["offroad-sim"].world_seed == SUITES["train-target-offroad"].world_seed
    assert SUITES["boreas-sim"].world_seed == SUITES["train-target-boreas"].world_seed
    hard = replace(SUITES["loop-sim-hard"], profile_overrides=(("road_half_width_m", 14.0),))
    prof = suite_profile(hard)
    assert prof.name == "urban-open" and prof.road_half_width_m == 14.0  # same name: same tile seeds
    assert Traversal.EGO_CLEARANCE_M == 7.0


def test_boreas_arterials_put_the_kerbs_8_m_from_the_centreline():
    """v7's Boreas override moves the kerbs (and so everything set back from them) from 6 m to 8 m on each side of
    a straight road: every kerb segment of a tile on the road lies at |y| = the profile's road half width."""
    road = straight_road(400.0)  # along y = 0
    for half in (6.0, 8.0):
        prof = replace(PROFILES["suburban"], road_half_width_m=half)
        prim = World(road, seed=3, profile=prof).tile(0, 0)
        kerb = prim.seg[(prim.seg_low == 1) & np.isclose(prim.seg[:, 1], prim.seg[:, 3])]
        assert len(kerb) > 5
        np.testing.assert_allclose(np.abs(kerb[:, [1, 3]]), half, atol=0.05)


def _window_peak(scan, az_deg: float, range_m: float) -> float:
    """Brightest bin within +-2 azimuths / +-0.8 m of (az_deg clockwise from forward, range_m)."""
    row = int(round(az_deg / 360.0 * scan.num_azimuths)) % scan.num_azimuths
    rows = [(row + k) % scan.num_azimuths for k in range(-2, 3)]
    b = int(round((range_m - scan.range_offset_m) / scan.range_resolution_m))
    w = int(0.8 / scan.range_resolution_m)
    return float(scan.power[rows, b - w:b + w + 1].max())


def test_hard_point_gain_scales_the_cross_section_in_db():
    """A pole's cross-section times 0.1 is 10 dB less: with the log compression (``db_span`` 100 dB per unit of
    image value) its bin drops by 0.1, the noise elsewhere stays; the default (1.0) leaves the scan as it was."""
    trav = Traversal(World(straight_road(), seed=0, profile="empty"), seed=1, traffic_per_km=0.0)
    extra = Primitives()
    extra.add_points(np.array([[30.0, 0.0]]), 40.0, 0)  # hard point 30 m ahead
    traj = linear_trajectory()
    base = render_scan(trav, traj, T0, "oxford", 5, CLEAN, extra=extra)
    same = render_scan(trav, traj, T0, "oxford", 5, replace(CLEAN, hard_point_gain=1.0), extra=extra)
    np.testing.assert_array_equal(base.power, same.power)
    dim = render_scan(trav, traj, T0, "oxford", 5, replace(CLEAN, hard_point_gain=0.1), extra=extra)
    drop = _window_peak(base, 0.0, 30.0) - _window_peak(dim, 0.0, 30.0)
    assert abs(drop - 10.0 / CLEAN.db_span) < 0.01
    np.testing.assert_array_equal(base.power[200:300], dim.power[200:300])  # behind the vehicle: noise only


def test_vehicle_elevation_scale_dims_cars_next_to_the_sensor_only():
    """A car's side 4 m to the right is lit through the ground's elevation pattern scaled by the option: at
    scale 1 its power gain is the ground's at 4 m (logistic((4 - 16) / 6) = 0.12, i.e. 9.2 dB less); the same
    car 60 m to the left keeps > 0.99 of its power. Kerbs and buildings are not cars."""
    world = World(straight_road(), seed=0, profile="empty")
    trav = Traversal(world, seed=1, traffic_per_km=0.0)
    extra = Primitives()
    extra.add_segments(np.array([[-2.3, -4.0, 2.3, -4.0], [-2.3, 60.0, 2.3, 60.0]]), 2.5, 0.0, 0.5, ELEV_VEHICLE)
    traj = linear_trajectory()
    v7 = render_scan(trav, traj, T0, "oxford", 5, CLEAN, extra=extra)
    tall = Primitives()
    tall.add_segments(extra.seg, 2.5, 0.0, 0.5)  # the same outline as a tall object
    np.testing.assert_array_equal(v7.power, render_scan(trav, traj, T0, "oxford", 5, CLEAN, extra=tall).power)
    low = render_scan(trav, traj, T0, "oxford", 5, replace(CLEAN, vehicle_elevation_scale=1.0), extra=extra)
    gain_4m = 1.0 / (1.0 + np.exp(-(4.0 - 16.0) / 6.0))
    drop_near = _window_peak(v7, 90.0, 4.0) - _window_peak(low, 90.0, 4.0)
    assert abs(drop_near - 10 * np.log10(1 / gain_4m) / CLEAN.db_span) < 0.01
    assert _window_peak(v7, 270.0, 60.0) - _window_peak(low, 270.0, 60.0) < 0.005


def test_facade_roughness_scale_scales_building_and_wall_roughness_only():
    """The specular-facade probe (issue 10): the option multiplies the roughness of building outlines and walls
    (1 = diffuse, 0 = specular) and changes no other draw; the default leaves every tile as it was."""
    road = straight_road(400.0)
    base = PROFILES["urban"]
    assert base.facade_roughness_scale == 1.0
    v10 = World(road, seed=1, profile=base).tile(1, 0)
    half = World(road, seed=1, profile=replace(base, facade_roughness_scale=0.5)).tile(1, 0)
    np.testing.assert_array_equal(half.seg, v10.seg)
    np.testing.assert_array_equal(half.seg_refl, v10.seg_refl)
    np.testing.assert_array_equal(half.pts, v10.pts)
    opaque = v10.seg_trans < 0.2  # building outlines and walls (opaque): scaled
    assert opaque.sum() > 10
    np.testing.assert_allclose(half.seg_rough[opaque], 0.5 * v10.seg_rough[opaque])
    np.testing.assert_array_equal(half.seg_rough[~opaque], v10.seg_rough[~opaque])  # kerbs, fences, rails
