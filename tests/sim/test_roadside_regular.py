"""Regular roadsides (``WorldProfile.roadside_regular``, issue 10 session 26 probe): the default leaves every tile
unchanged; at 1 every roadside is lined by rows of equal street trees and lamp posts at the promised spacings and
setbacks, running on across tiles at one phase. Known answers on a straight road."""

from __future__ import annotations

from dataclasses import fields, replace

import numpy as np

from reradar_core.sim.world import PROFILES, Primitives, World

from .conftest import straight_road


def _assert_same(a: Primitives, b: Primitives) -> None:
    for f in fields(Primitives):
        np.testing.assert_array_equal(getattr(a, f.name), getattr(b, f.name), err_msg=f.name)


def test_default_leaves_every_tile_unchanged():
    road = straight_road(400.0)  # x from -200 to 200 along y = 0
    for name in ("urban-open", "offroad", "urban"):
        base = PROFILES[name]
        assert base.roadside_regular == 0.0
        # the row parameters do nothing while the share is 0
        other = replace(base, roadside_regular=0.0, roadside_tree_spacing_m=7.0, roadside_pole_spacing_m=11.0,
                        roadside_tree_setback_m=1.0, roadside_facade_setback_m=9.0)
        for ix, iy in ((-5, -1), (-1, 0), (2, 0), (4, -1), (1, 3)):
            _assert_same(World(road, seed=3, profile=base).tile(ix, iy), World(road, seed=3, profile=other).tile(ix, iy))


def test_regular_rows_stand_at_the_promised_spacing_and_setback():
    road = straight_road(400.0)  # samples every 2 m from x = -200: slot k of a row at x = -200 + k * spacing
    prof = replace(PROFILES["empty"], road_half_width_m=6.0, street_tree_prob=1.0, pole_spacing_m=9.0,
                   roadside_regular=1.0, roadside_tree_spacing_m=10.0, roadside_tree_setback_m=3.0,
                   roadside_tree_radius_m=2.0, roadside_pole_spacing_m=30.0, roadside_pole_setback_m=1.0)
    world = World(road, seed=5, profile=prof)
    prim = Primitives.concat([world.tile(ix, iy) for ix in range(-5, 5) for iy in (-1, 0)])
    trees = prim.disc[prim.disc[:, 2] > 1.0]
    poles = prim.disc[prim.disc[:, 2] < 1.0]
    # every tree of the row and nothing else: both sides, 9 m off the centreline, every 10 m, radius 2 m
    np.testing.assert_allclose(np.unique(np.abs(trees[:, 1])), [9.0])
    np.testing.assert_allclose(trees[:, 2], 2.0)
    for side in (1.0, -1.0):
        x = np.sort(trees[np.sign(trees[:, 1]) == side, 0])
        np.testing.assert_allclose(x, -200.0 + 10.0 * np.arange(len(x)))  # -200 .. 190, one phase across tiles
        assert len(x) == 40
        xp = np.sort(poles[np.sign(poles[:, 1]) == side, 0])
        np.testing.assert_allclose(xp, -200.0 + 30.0 * np.arange(14))  # lamp posts every 30 m
    np.testing.assert_allclose(np.abs(poles[:, 1]), 7.0)
    # the random street trees and poles of the same profile without rows stand elsewhere
    rnd = replace(prof, roadside_regular=0.0)
    prim0 = Primitives.concat([World(road, seed=5, profile=rnd).tile(ix, iy) for ix in range(-5, 5) for iy in (-1, 0)])
    assert len(prim0.disc) > 0
    assert not np.all(np.isin(np.round(np.abs(prim0.disc[:, 1]), 6), [7.0, 9.0]))


def test_regular_frontage_has_a_constant_setback_and_a_share_of_sides():
    road = straight_road(2000.0)
    prof = replace(PROFILES["empty"], road_half_width_m=6.0, frontage_prob=1.0, roadside_regular=1.0,
                   roadside_facade_setback_m=4.75, roadside_tree_spacing_m=0.0, roadside_pole_spacing_m=0.0)
    world = World(road, seed=2, profile=prof)
    n_lines = 0
    for ix in range(-20, 20):
        seg = world.tile(ix, 0).seg  # the road (y = 0) lies in the tiles iy = 0; they hold its roadsides
        for side in (1.0, -1.0):
            front = seg[np.sign(seg[:, 1]) == side]
            if len(front):  # the main building line at 6 + 4.75 m; recesses only further back
                n_lines += 1
                assert np.isclose(np.abs(front[:, [1, 3]]).min(), 10.75)
    assert n_lines >= 60  # of 80 tile sides (gaps between buildings may empty a few)
    # a share of 0.5 lines about half the tile sides with rows (a hash per tile and side)
    half = World(road, seed=2, profile=replace(PROFILES["empty"], road_half_width_m=6.0, roadside_regular=0.5))
    trees = np.concatenate([half.tile(ix, iy).disc for ix in range(-25, 25) for iy in (-1, 0)])
    n_sides = len(np.unique(np.column_stack([np.floor(trees[:, 0] / 40.0), np.sign(trees[:, 1])]), axis=0))
    assert 30 <= n_sides <= 70  # of 100 tile sides


def test_jitter_moves_each_row_object_within_its_bound_and_keeps_the_count():
    road = straight_road(400.0)
    prof = replace(PROFILES["empty"], road_half_width_m=6.0, roadside_regular=1.0, roadside_tree_spacing_m=10.0,
                   roadside_tree_setback_m=3.0, roadside_pole_spacing_m=0.0)
    exact = np.concatenate([World(road, seed=5, profile=prof).tile(ix, 0).disc for ix in range(-5, 5)])
    moved = np.concatenate([World(road, seed=5, profile=replace(prof, roadside_jitter_m=1.5)).tile(ix, 0).disc
                            for ix in range(-5, 5)])
    assert len(moved) == len(exact) == 80
    def by_side_then_x(d: np.ndarray) -> np.ndarray:  # 10 m apart along each row: jitter keeps the order
        return d[np.lexsort((d[:, 0], np.sign(d[:, 1])))][:, :2]

    delta = by_side_then_x(moved) - by_side_then_x(exact)
    assert np.abs(delta).max() <= 1.5 and np.abs(delta).max() > 0.5
    assert len(np.unique(np.round(np.abs(moved[:, 1]), 6))) > 40  # no longer one setback
