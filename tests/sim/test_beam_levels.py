"""Beam-level options of the sensor (session 17 probe): a receive gain and a noise-floor level per azimuth, and a
range skirt along each beam. Each defaults to off with renders unchanged; known answers on an empty world."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from reradar_core.io.presets import get_preset
from reradar_core.sim.sensor import SensorConfig, _azimuth_jitter, _range_skirt, render_scan
from reradar_core.sim.stats import beam_level_persistence, beam_level_statistics
from reradar_core.sim.traversal import Traversal
from reradar_core.sim.world import World

from .conftest import CLEAN, T0, linear_trajectory, straight_road


def _render(cfg: SensorConfig, profile: str = "urban", seed: int = 11):
    world = World(straight_road(600.0), seed=3, profile=profile)
    trav = Traversal(world, seed=4, traffic_per_km=0.0)
    return render_scan(trav, linear_trajectory(), T0, get_preset("oxford"), seed, cfg)


def test_options_default_off_and_leave_the_render_unchanged():
    cfg = SensorConfig()
    assert cfg.azimuth_gain_db == 0.0 and cfg.azimuth_floor_db == 0.0 and cfg.skirt_dbc is None
    base = _render(CLEAN)
    same = _render(replace(CLEAN, azimuth_gain_coupling=0.3, skirt_r0_m=5.0))  # inert without their levels
    np.testing.assert_array_equal(base.power, same.power)


def test_azimuth_jitter_has_the_stated_spread_and_coupling():
    rng = np.random.default_rng(0)
    db = 10 * np.log10(np.concatenate([_azimuth_jitter(rng, 400, 2.0, 0.0) for _ in range(50)]))
    assert abs(db.mean()) < 0.05 and abs(db.std() - 2.0) < 0.05
    rng = np.random.default_rng(1)
    g = np.stack([10 * np.log10(_azimuth_jitter(rng, 400, 1.0, 0.5)) for _ in range(50)])
    lag1 = np.mean([np.corrcoef(r, np.roll(r, 1))[0, 1] for r in g])
    assert abs(lag1 - 2 * 0.5 / (1 + 2 * 0.25)) < 0.03  # 2c / (1 + 2c^2)
    assert abs(g.std() - 1.0) < 0.03  # rescaled to the given spread


def test_gain_jitter_shifts_whole_beams_in_the_log_scale():
    cfg = replace(CLEAN, streak_rate=0.0)
    base, jit = _render(cfg), _render(replace(cfg, azimuth_gain_db=2.0))
    # a gain of g dB adds g / db_span to every unclipped bin of its beam: per-beam median shift ~ N(0, 2 dB)
    on = (base.power > 0.05) & (jit.power > 0.05)
    shift_db = np.array([np.median((jit.power[a] - base.power[a])[on[a]]) for a in range(400) if on[a].sum() > 50])
    shift_db *= cfg.db_span
    assert len(shift_db) > 300 and abs(shift_db.std() - 2.0) < 0.25 and abs(shift_db.mean()) < 0.3
    assert beam_level_statistics(jit).level_jitter > 1.5 * beam_level_statistics(base).level_jitter


def test_floor_jitter_moves_the_noise_not_the_targets():
    cfg = replace(CLEAN, speckle_looks=0.0)  # no speckle: the noise-only bins are the floor itself
    base, jit = _render(cfg, profile="empty"), _render(replace(cfg, azimuth_floor_db=3.0), profile="empty")
    r = base.ranges_m
    far = (r > 120) & (r < 160)  # an empty world: ground and floor only
    shift = (jit.power[:, far] - base.power[:, far]).mean(axis=1) * cfg.db_span  # dB, where the floor dominates
    assert shift.std() > 1.0
    # the near field (self-return, 11x the floor) moves by a fraction of that: log10(11 + f) vs log10(1 + f)
    near = r < 1.0
    near_shift = (jit.power[:, near] - base.power[:, near]).mean(axis=1) * cfg.db_span
    assert near_shift.std() < 0.25 * shift.std()


def test_range_skirt_spreads_a_return_along_its_own_beam_only():
    cfg = replace(SensorConfig(), skirt_dbc=-30.0, skirt_r0_m=1.0, skirt_exponent=2.0)
    target = np.zeros((4, 200), np.float32)
    target[1, 50] = 1000.0
    s = _range_skirt(target, 0.5, cfg)
    assert np.all(s[[0, 2, 3]] == 0)  # other beams untouched
    # 10^-3 * 1000 * (1 + dr / 1 m)^-2 at dr = 0, 1, 5 m (0.5 m bins)
    np.testing.assert_allclose(s[1, [50, 52, 60]], [1.0, 0.25, 1 / 36], rtol=1e-4)
    np.testing.assert_allclose(s[1, 40], s[1, 60], rtol=1e-4)  # symmetric


def test_beam_level_statistics_known_answer():
    from reradar_core.io.scan import RadarScan

    p = get_preset("oxford")
    rng = np.random.default_rng(0)
    scene = rng.uniform(20, 40, p.num_range_bins)  # the same range profile in every beam: no beam-to-beam jump
    flat = RadarScan.from_power((np.tile(scene, (400, 1)) / 255.0).astype(np.float32), "oxford")
    s0 = beam_level_statistics(flat)
    assert s0.level_jitter < 1e-6 and s0.far_jitter < 1e-6
    # every other beam one step brighter over its whole length: high-passed +-(1 - 1/9) steps, coupled, lag-1 = -1
    step = np.where(np.arange(400) % 2 == 0, 1.0, -1.0)[:, None]
    alt = RadarScan.from_power(((np.tile(scene, (400, 1)) + step) / 255.0).astype(np.float32), "oxford")
    s = beam_level_statistics(alt)
    assert abs(s.level_jitter - 8 / 9) < 1e-3 and abs(s.far_jitter - 8 / 9) < 1e-3
    assert s.band_coupling > 0.999 and s.lag1 < -0.999


def test_beam_level_persistence_tells_scene_from_fresh_draws():
    from reradar_core.io.scan import RadarScan

    rng = np.random.default_rng(3)
    n_r = get_preset("oxford").num_range_bins
    scene = rng.normal(0.0, 3.0, 400)[:, None]  # the same per-beam level in every scan: a scene that stays
    same = [RadarScan.from_power(((30.0 + scene + np.zeros((1, n_r))) / 255.0).astype(np.float32), "oxford")
            for _ in range(4)]
    fresh = [RadarScan.from_power(((30.0 + rng.normal(0.0, 3.0, (400, 1)) + np.zeros((1, n_r))) / 255.0)
                                  .astype(np.float32), "oxford") for _ in range(4)]
    assert beam_level_persistence(same, 1) > 0.999
    assert abs(beam_level_persistence(fresh, 1)) < 0.2


def test_beam_level_statistics_refuses_a_scan_without_a_far_range():
    import pytest

    from reradar_core.io.scan import RadarScan

    short = RadarScan.from_power(np.full((400, 1000), 0.1, np.float32), "oxford")  # 1000 x 4.38 cm = 44 m
    with pytest.raises(ValueError, match="beyond 100 m"):
        beam_level_statistics(short)
