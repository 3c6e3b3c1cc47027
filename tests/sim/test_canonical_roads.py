"""``canonical_roads``: a world that depends on the set of roads, not on their order or driving direction (QA,
session 21: ``reradar sim --road`` built a different world for a drive and its reverse)."""

from __future__ import annotations

import numpy as np

from reradar_core.sim.world import RoadNetwork, canonical_roads


def _curve(n: int = 61, lateral: float = 0.0) -> np.ndarray:
    s = np.linspace(0.0, 150.0, n)
    return np.column_stack([s, 20.0 * np.sin(s / 40.0) + lateral])


def test_order_and_direction_do_not_change_the_road_network() -> None:
    a, b = _curve(), _curve(37, lateral=30.0)
    # the defect: a road and its reverse, listed the other way round, are sampled from different ends
    raw_ab, raw_ba = RoadNetwork([a, a[::-1]]), RoadNetwork([a[::-1], a])
    assert raw_ab.points.shape != raw_ba.points.shape or not np.allclose(raw_ab.points, raw_ba.points)
    ref = RoadNetwork(canonical_roads([a, b]))
    for roads in ([a, a[::-1], b], [a[::-1], b], [b[::-1], a], [b, a[::-1], a]):
        net = RoadNetwork(canonical_roads(roads))
        np.testing.assert_array_equal(net.points, ref.points)
        np.testing.assert_array_equal(net.tangents, ref.tangents)


def test_canonical_roads_keeps_the_points_and_orients_a_loop_counter_clockwise() -> None:
    t = np.linspace(0.0, 2.0 * np.pi, 50)
    loop_cw = np.column_stack([np.cos(-t), np.sin(-t)]) * 100.0
    loop_cw[-1] = loop_cw[0]
    (out,) = canonical_roads([loop_cw])
    np.testing.assert_array_equal(out, loop_cw[::-1])  # turned counter-clockwise, same points
    line = np.array([[5.0, 0.0], [0.0, 0.0]])
    (back,) = canonical_roads([line])
    np.testing.assert_array_equal(back, line[::-1])  # runs from the smaller end point
    longer, shorter = canonical_roads([line, loop_cw])
    assert len(longer) == 50 and len(shorter) == 2  # longer roads first: their samples are kept
