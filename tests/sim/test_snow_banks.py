"""Snow-bank options (diagnosis of ReFeree / RingKey on boreas-sim, docs/SIMULATOR.md): the beam share
passing a bank and the share of the bank pattern drawn anew per traversal. Defaults are simulator v4's."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from reradar_core.sim.sensor import render_scan
from reradar_core.sim.traversal import Traversal
from reradar_core.sim.world import PROFILES, Primitives, World

from .conftest import CLEAN, T0, linear_trajectory

#: no structures, but kerbs (snow banks are ploughed only where the profile has kerbs)
KERBED = replace(PROFILES["empty"], name="empty-kerbed", kerb_reflectivity=0.06)


def _banks(world: World, seed: int, transmission: float | None = None,
           daily: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    trav = Traversal(world, seed, "snow_cover", traffic_per_km=0.0)
    if transmission is not None:
        trav.SNOW_BANK_TRANSMISSION = transmission
    if daily is not None:
        trav.SNOW_BANK_DAILY_FRACTION = daily
    dyn = trav.dynamic_primitives(0.0, np.zeros(2), 150.0, Primitives())
    return dyn.seg, dyn.seg_trans


def _present(seg: np.ndarray, all_mid: np.ndarray) -> np.ndarray:
    mid = {tuple(np.round(0.5 * (s[:2] + s[2:]), 3)) for s in seg}
    return np.array([tuple(m) in mid for m in all_mid])


def test_v4_defaults_unchanged():
    assert Traversal.SNOW_BANK_TRANSMISSION == 0.6
    assert Traversal.SNOW_BANK_DAILY_FRACTION == 1.0
    assert Traversal.SNOW_BANK_REFLECTIVITY == 0.6


def test_bank_pattern_shared_share_between_traversals(road):
    """Presence agreement between two traversals: a sample drawn per day agrees with probability
    0.7^2 + 0.3^2 = 0.58; a shared one always. Expected agreement = (1 - f) + 0.58 f."""
    world = World(road, seed=5, profile=KERBED)
    # every possible sample: union of the banks of many traversals
    segs = [_banks(world, s)[0] for s in range(12)]
    all_mid = np.unique(np.round(np.concatenate([0.5 * (g[:, :2] + g[:, 2:]) for g in segs]), 3), axis=0)
    assert len(all_mid) > 250  # two sides of ~300 m of road, one sample per 2 m road step
    for f, expect in [(1.0, 0.58), (0.5, 0.79), (0.0, 1.0)]:
        agree = []
        for a, b in [(1, 2), (3, 4), (5, 6)]:
            pa = _present(_banks(world, a, daily=f)[0], all_mid)
            pb = _present(_banks(world, b, daily=f)[0], all_mid)
            assert 0.62 < pa.mean() < 0.78  # 70 % of samples carry a bank whatever f
            agree.append(np.mean(pa == pb))
        assert abs(np.mean(agree) - expect) < 0.05, (f, agree)
    # f = 0: one pattern per world, identical on every traversal; another world has its own
    s1, _ = _banks(world, 1, daily=0.0)
    s2, _ = _banks(world, 99, daily=0.0)
    np.testing.assert_array_equal(s1, s2)
    other = _present(_banks(World(road, seed=6, profile=KERBED), 1, daily=0.0)[0], all_mid)
    assert np.mean(other == _present(s1, all_mid)) < 0.7


def test_bank_transmission_dims_what_lies_behind_by_its_two_way_square(road):
    """A pole behind a bank: rendered with transmission T and with 1.0 (nothing else differs, same speckle),
    its 8-bit value drops by 10 log10(T^2) / db_span: 0.0444 for T = 0.6 (v4), 0.0092 for 0.9, 0 for 1."""
    world = World(road, seed=5, profile=KERBED)
    seg, tr = _banks(world, 1, daily=0.0)
    np.testing.assert_allclose(tr, 0.6)  # v4 default
    np.testing.assert_allclose(_banks(world, 1, transmission=0.9, daily=0.0)[1], 0.9)
    # a bank sample on the right-hand kerb (y < 0) near the sensor; the pole 30 m out along the ray through it
    mids = 0.5 * (seg[:, :2] + seg[:, 2:])
    right = mids[(mids[:, 1] < 0) & (np.abs(mids[:, 0]) < 3.0)]
    pick = right[np.argmin(np.abs(right[:, 0]))]
    # the ray through the middle of a 2 m bank sample: the beam (1.8 deg, 0.2 m wide there) stays inside it
    pole_xy = pick / np.hypot(*pick) * 30.0
    pole = Primitives()
    pole.add_points(pole_xy[None], 4.0, 0)
    az = float(np.degrees(np.mod(np.arctan2(-pole_xy[1], pole_xy[0]), 2 * np.pi)))
    row = int(round(az / 0.9)) % 400

    def pole_value(t: float) -> float:
        trav = Traversal(world, 1, "snow_cover", traffic_per_km=0.0)
        trav.SNOW_BANK_TRANSMISSION, trav.SNOW_BANK_DAILY_FRACTION = t, 0.0
        scan = render_scan(trav, linear_trajectory(), T0, "oxford", 11, CLEAN, extra=pole)
        b = int(round(30.0 / scan.range_resolution_m))
        return float(scan.power[row, b - 10:b + 11].max())

    v1 = pole_value(1.0)
    assert v1 > 0.3
    for t in (0.6, 0.9):
        expect = -10 * np.log10(t * t) / 100.0  # db_span 100 dB over the 8-bit range
        assert abs((v1 - pole_value(t)) - expect) < 0.006, (t, v1, expect)
