"""Open land and ground clutter that does not persist (``WorldProfile.open_share`` / ``open_scale_m`` /
``open_clutter_persistence`` / ``ground_clutter_persistence`` / ``ground_clutter_redraw``; issue 10, session 32):
the defaults leave every tile unchanged; open land covers the promised share of the roads and holds nothing but
ground clutter; clutter that does not persist is drawn with the same density, the same within a traversal (or a
scan) and different on another."""

from __future__ import annotations

from dataclasses import fields, replace

import numpy as np
import pytest

from reradar_core.errors import ConfigError
from reradar_core.sim.traversal import Traversal
from reradar_core.sim.world import PROFILES, Primitives, RoadNetwork, World

from .conftest import straight_road


def _assert_same(a: Primitives, b: Primitives) -> None:
    for f in fields(Primitives):
        np.testing.assert_array_equal(getattr(a, f.name), getattr(b, f.name), err_msg=f.name)


def _winding_road() -> RoadNetwork:
    """A 12 km meander: it crosses many 600 m cells of the open-land field."""
    s = np.linspace(0.0, 12000.0, 3000)
    return RoadNetwork([np.column_stack([s * np.cos(0.3), 900.0 * np.sin(s / 700.0) + s * np.sin(0.3)])])


def test_defaults_leave_every_tile_unchanged():
    road = straight_road(400.0)
    for name in ("offroad", "urban-open", "urban"):
        base = PROFILES[name]
        assert base.open_share == 0.0 and base.ground_clutter_persistence == 1.0
        assert base.open_clutter_persistence == 1.0
        # the other open-land parameters do nothing while the share is 0 and the persistence 1
        other = replace(base, open_scale_m=50.0, open_clutter_persistence=0.0, ground_clutter_redraw="scan")
        w0, w1 = World(road, seed=3, profile=base), World(road, seed=3, profile=other)
        assert not w1.has_transient_clutter()
        for ix, iy in ((-5, -1), (-1, 0), (2, 0), (4, -1), (1, 3)):
            _assert_same(w0.tile(ix, iy), w1.tile(ix, iy))
        trav = Traversal(w1, seed=1, traffic_per_km=0.0)
        assert len(trav.dynamic_primitives(0.0, np.zeros(2), 150.0, w1.query(np.zeros(2), 150.0)).pts) == 0


def test_open_land_covers_the_share_of_the_roads_and_holds_only_ground_clutter():
    road = _winding_road()
    base = PROFILES["offroad"]
    for share in (0.2, 0.35):
        world = World(road, seed=7, profile=replace(base, open_share=share, open_scale_m=600.0))
        pts = road.points[::3]
        is_open = np.array([world.is_open_land(p) for p in pts])
        assert abs(is_open.mean() - share) < 0.02
        # what renders is decided per 40 m tile, at its centre: the road's share through open tiles is the same
        tiles = np.floor(pts / world.tile_m).astype(int)
        assert abs(np.mean([world.tile_is_open(int(i), int(j)) for i, j in tiles]) - share) < 0.03
    everywhere = World(road, seed=7, profile=replace(base, open_share=1.0))
    assert all(everywhere.tile_is_open(int(i), int(j)) for i, j in np.floor(road.points[::50] / 40.0).astype(int))
    world = World(road, seed=7, profile=replace(base, open_share=0.35, open_scale_m=600.0))
    plain = World(road, seed=7, profile=base)
    n_open = n_closed = 0
    for p in road.points[::40]:
        ix, iy = (int(np.floor(c / world.tile_m)) for c in p)
        centre = (np.array([ix, iy]) + 0.5) * world.tile_m
        tile = world.tile(ix, iy)
        if world.is_open_land(centre):
            n_open += 1
            # no trees, hedges, terrain, buildings, walls or fences; the track's posts (every 150 m) and the
            # sign plates on some of them (0.8 m segments) remain
            assert np.all(np.hypot(*(tile.seg[:, 2:] - tile.seg[:, :2]).T) < 0.81) and np.all(tile.disc[:, 2] < 0.5)
            assert np.sum(tile.pts_kind == 2) > 0 and np.isin(tile.pts_kind, (0, 2)).all()  # clutter and posts
            assert np.sum(tile.pts_kind == 0) == len(tile.disc)
        else:
            n_closed += 1
            _assert_same(tile, plain.tile(ix, iy))  # the rest of the world is as without open land
    assert n_open > 5 and n_closed > 5


def test_transient_clutter_keeps_the_density_and_is_drawn_per_traversal_or_per_scan():
    road = straight_road(1200.0)
    base = replace(PROFILES["offroad"], tree_per_tile=0.0, hedge_per_tile=0.0, terrain_ridges_per_tile=0.0,
                   street_tree_prob=0.0, fence_per_tile=0.0, building_prob_per_tile=0.0, building_far_prob=0.0,
                   wall_per_tile=0.0, pole_spacing_m=1e12)
    fixed = World(road, seed=2, profile=base)
    half = World(road, seed=2, profile=replace(base, ground_clutter_persistence=0.5))
    none = World(road, seed=2, profile=replace(base, ground_clutter_persistence=0.0))
    centre, radius = np.zeros(2), 100.0
    n_fixed = len(fixed.query(centre, radius).pts)
    assert n_fixed > 5000
    # persistence 0.5 keeps about half of the same points; 0 keeps none
    kept = half.query(centre, radius).pts
    assert abs(len(kept) / n_fixed - 0.5) < 0.03
    assert np.isin(kept[:, 0], fixed.query(centre, radius).pts[:, 0]).all()
    assert len(none.query(centre, radius).pts) == 0

    def transient(world: World, seed: int, t_s: float) -> np.ndarray:
        trav = Traversal(world, seed=seed, traffic_per_km=0.0)
        return trav.dynamic_primitives(t_s, centre, radius, world.query(centre, radius + 15.0)).pts

    a, b, c = transient(none, 1, 0.0), transient(none, 1, 5.0), transient(none, 2, 0.0)
    # the same density as the fixed clutter (the dynamic query reaches 15 m farther; same tiles here)
    assert abs(len(a) / len(fixed.query(centre, radius + 15.0).pts) - 1.0) < 0.05
    np.testing.assert_array_equal(a, b)  # one traversal: the same clutter at every scan
    assert not np.isin(c[:, 0], a[:, 0]).any()  # another traversal: other clutter
    per_scan = World(road, seed=2, profile=replace(base, ground_clutter_persistence=0.0, ground_clutter_redraw="scan"))
    d, e = transient(per_scan, 1, 0.0), transient(per_scan, 1, 0.25)
    assert abs(len(d) / len(a) - 1.0) < 0.05
    assert not np.isin(d[:, 0], e[:, 0]).any()  # drawn anew at every scan


def test_open_land_clutter_only_is_transient_there():
    road = _winding_road()
    prof = replace(PROFILES["offroad"], open_share=0.35, open_scale_m=600.0, open_clutter_persistence=0.0)
    world = World(road, seed=7, profile=prof)
    assert world.has_transient_clutter()
    for p in road.points[::60]:
        ix, iy = (int(np.floor(c / world.tile_m)) for c in p)
        centre = (np.array([ix, iy]) + 0.5) * world.tile_m
        expected = 0.0 if world.is_open_land(centre) else 1.0
        assert world.clutter_persistence(ix, iy) == expected
        if expected == 0.0:  # no clutter fixed in the world there (the track's posts remain)
            assert not np.any(world.tile(ix, iy).pts_kind == 2)


def test_open_land_keeps_the_terrain_only_when_asked():
    road = _winding_road()
    flat = World(road, seed=7, profile=replace(PROFILES["offroad"], open_share=0.35, open_scale_m=600.0))
    hilly = World(road, seed=7, profile=replace(flat.profile, open_terrain=1.0))
    n_ridges = 0
    for p in road.points[::40]:
        ix, iy = (int(np.floor(c / flat.tile_m)) for c in p)
        if not flat.is_open_land((np.array([ix, iy]) + 0.5) * flat.tile_m):
            continue
        ridges = hilly.tile(ix, iy).seg_low == 1.0  # terrain ridges are low segments (no kerbs off-road)
        n_ridges += int(ridges.sum())
        assert not np.any(flat.tile(ix, iy).seg_low == 1.0)
        assert len(hilly.tile(ix, iy).disc) == len(flat.tile(ix, iy).disc)  # still no trees
    assert n_ridges > 20



def test_bad_settings_are_refused_by_name():
    road = straight_road(400.0)
    for bad, name in ((dict(ground_clutter_redraw="daily"), "ground_clutter_redraw"),
                      (dict(open_share=1.5), "open_share"), (dict(ground_clutter_persistence=-0.1),
                                                            "ground_clutter_persistence"),
                      (dict(open_clutter_persistence=2.0), "open_clutter_persistence"),
                      (dict(open_share=0.2, open_scale_m=0.0), "open_scale_m"),
                      (dict(open_terrain=-1.0), "open_terrain")):
        with pytest.raises(ConfigError, match=name):
            World(road, seed=1, profile=replace(PROFILES["offroad"], **bad))


def test_zone_factors_keep_their_mean_and_bounds():
    """The land-use zones (simulator v6, shared with the open-land field's value noise): factor 1 +- contrast, mean 1."""
    world = World(straight_road(400.0), seed=3, profile=replace(PROFILES["offroad"], zone_contrast=0.8))
    f = np.array([world.zone_factors(np.array([x, y])) for x in np.arange(0.0, 3000.0, 37.0)
                  for y in np.arange(0.0, 3000.0, 41.0)])
    assert f.min() >= 0.2 - 1e-12 and f.max() <= 1.8 + 1e-12
    assert abs(f.mean() - 1.0) < 0.05
    assert f[:, 0].std() > 0.1 and abs(np.corrcoef(f[:, 0], f[:, 1])[0, 1]) < 0.3  # two independent fields


def test_rendered_scans_in_open_land_change_with_the_traversal_only():
    """Through the sensor: the same scan renders identically; another traversal's open-land clutter differs."""
    from reradar_core.sim.sensor import render_scan, scan_seed

    from .conftest import CLEAN, T0, linear_trajectory

    road = straight_road(1200.0)
    base = replace(PROFILES["offroad"], open_share=1.0, open_clutter_persistence=0.0, tree_per_tile=0.0)
    world = World(road, seed=2, profile=base)
    traj = linear_trajectory(speed_mps=5.0)

    def scan(seed: int, profile=base) -> np.ndarray:
        w = world if profile is base else World(road, seed=2, profile=profile)
        return render_scan(Traversal(w, seed=seed, traffic_per_km=0.0), traj, T0, "oxford", scan_seed(1, 0),
                           CLEAN).power
    a, b, c = scan(1), scan(1), scan(2)
    np.testing.assert_array_equal(a, b)
    assert np.mean(a != c) > 0.05  # other heather, other returns
    fixed = replace(base, open_clutter_persistence=1.0)
    np.testing.assert_array_equal(scan(1, fixed), scan(2, fixed))  # fixed clutter: the traversal does not matter

