"""Motion compensation (``matching.motion``): azimuth times, de-skewing, a map drive's motion, and the pose of a scan
seen from a moving sensor recovered where the rigid registration keeps the skew as error."""

from __future__ import annotations

import math

import numpy as np
import pytest

from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.se2 import compose, inverse, relative_pose, transform_points, wrap_angle
from reradar_core.localization import InMemoryKeyframes, LocalizationConfig, Localizer, PosePrior
from reradar_core.matching.motion import (
    MotionConfig,
    azimuth_time_offsets,
    deskew_points,
    keyframe_twists,
    motion_polish,
    odometry_twist,
)
from reradar_core.matching.ransac import fit_rigid_2d
from reradar_core.retrieval import GlobalIndex

T_SWEEP = 0.25
MID = 399 / 800 * T_SWEEP  # mid-sweep time after the first azimuth, 400 azimuths


def test_azimuth_times_run_clockwise_from_straight_ahead() -> None:
    xy = np.array([[10.0, 0.0], [0.0, -10.0], [-10.0, 0.0], [0.0, 10.0]])  # ahead, right, behind, left
    np.testing.assert_allclose(azimuth_time_offsets(xy), np.array([0.0, 0.25, 0.5, 0.75]) * T_SWEEP - MID,
                               atol=1e-12)


def test_deskew_moves_points_by_the_motion_at_their_time() -> None:
    xy = np.array([[0.0, -10.0], [0.0, 10.0]])  # right (seen early), left (seen late)
    tau = azimuth_time_offsets(xy)
    moved = deskew_points(xy, tau, np.array([10.0, 0.0, 0.0]))  # 10 m/s forward
    np.testing.assert_allclose(moved[:, 0], 10.0 * tau, atol=1e-12)
    turned = deskew_points(np.array([[20.0, 0.0]]), np.array([0.1]), np.array([0.0, 0.0, 0.5]))
    np.testing.assert_allclose(turned, [[20.0 * math.cos(0.05), 20.0 * math.sin(0.05)]], atol=1e-12)


def test_keyframe_twists_from_a_drive_on_a_circle() -> None:
    # 8 m/s on a circle of radius 40 m (0.2 rad/s), a keyframe every 0.75 s; one keyframe 10 s later alone
    t = np.arange(8) * 0.75
    th = 0.2 * t
    poses = np.column_stack([40 * np.sin(th), 40 * (1 - np.cos(th)), th])
    poses = np.vstack([poses, [500.0, 0.0, 0.0]])
    stamps = (np.append(t, 30.0) * 1e6).astype(np.int64)
    twists, known = keyframe_twists(poses[::-1], stamps[::-1])  # any order
    twists, known = twists[::-1], known[::-1]
    assert known[:8].all() and not known[8]
    # exact under constant motion: 8 m/s forward, nothing sideways, 0.2 rad/s - at the ends (one neighbour) too
    np.testing.assert_allclose(twists[:8], np.tile([8.0, 0.0, 0.2], (8, 1)), atol=1e-9)
    np.testing.assert_array_equal(twists[8], 0.0)
    # made-up times (poses 50 m apart 1 us apart) are no drive: unknown
    _, known = keyframe_twists(np.column_stack([np.arange(4) * 50.0, np.zeros(4), np.zeros(4)]), np.arange(4))
    assert not known.any()


def _seen_from(world_xy: np.ndarray, T_world_sensor: np.ndarray, twist: np.ndarray) -> np.ndarray:
    """Where a sensor at ``T_world_sensor`` (mid-sweep) moving with ``twist`` sees world points (the inverse of
    ``deskew_points`` after ``transform_points``, solved by fixed-point iteration on each point's azimuth time)."""
    local = transform_points(inverse(T_world_sensor), world_xy)
    seen = local.copy()
    for _ in range(20):
        tau = azimuth_time_offsets(seen)
        w = twist[2] * tau
        shifted = local - np.outer(tau, twist[:2])
        seen = np.column_stack([np.cos(-w) * shifted[:, 0] - np.sin(-w) * shifted[:, 1],
                                np.sin(-w) * shifted[:, 0] + np.cos(-w) * shifted[:, 1]])
    return seen


def _street(rng: np.random.Generator, n: int = 600) -> np.ndarray:
    """World landmarks along a 200 m street (x), both sides and some far returns, none near the x axis ahead
    (the sweep's seam, where a point's time jumps by a sweep)."""
    x = rng.uniform(-100, 100, n)
    y = np.where(rng.random(n) < 0.5, 1.0, -1.0) * rng.uniform(6, 40, n)
    return np.column_stack([x, y])


def test_motion_polish_recovers_the_pose_the_skew_hides() -> None:
    rng = np.random.default_rng(3)
    world = _street(rng)
    T_w_kf = np.array([0.0, 0.0, 0.0])
    kf_twist = np.array([10.0, 0.0, 0.0])  # the map drive at 10 m/s east
    T_w_q = np.array([2.0, 3.5, math.pi + 0.03])  # the query drives the other way, 3.5 m over
    q_twist = np.array([9.0, 0.0, 0.2])  # 9 m/s, turning at 11 deg/s
    kf_seen = _seen_from(world, T_w_kf, kf_twist)
    q_seen = _seen_from(world, T_w_q, q_twist) + rng.normal(scale=0.03, size=world.shape)
    truth = relative_pose(T_w_kf, T_w_q)
    # the rigid fit of the skewed scans (what the registration answers) misses by the skew
    rigid = fit_rigid_2d(q_seen, kf_seen)
    assert np.hypot(*(rigid[:2] - truth[:2])) > 0.2
    polished = motion_polish(q_seen, kf_seen, rigid, kf_twist)
    assert polished is not None and polished.num_associated > 500
    assert np.hypot(*(polished.T_dst_src[:2] - truth[:2])) < 0.03
    assert abs(polished.T_dst_src[2] - truth[2]) < math.radians(0.05)
    np.testing.assert_allclose(polished.twist, q_twist, atol=0.3)


def test_motion_polish_reaches_a_fast_drive_the_other_way() -> None:
    # both drives at 25 m/s, the query the other way: the skews pull the rigid pose along the track by more than the
    # fine radii reach (the registration answered 1.4-2.8 m off at 20-30 m/s, session 30's QA)
    rng = np.random.default_rng(7)
    world = _street(rng)
    kf_twist = np.array([25.0, 0.0, 0.0])
    T_w_q = np.array([1.0, 3.5, math.pi])
    kf_seen = _seen_from(world, np.zeros(3), kf_twist)
    q_seen = _seen_from(world, T_w_q, np.array([25.0, 0.0, 0.0])) + rng.normal(scale=0.03, size=world.shape)
    truth = relative_pose(np.zeros(3), T_w_q)
    start = truth + np.array([1.6, 0.0, 0.0])  # along the track, as the registration answers
    fine_only = motion_polish(q_seen, kf_seen, start, kf_twist, MotionConfig(radii_m=(0.75, 0.6, 0.5, 0.4)))
    assert fine_only is None or np.hypot(*(fine_only.T_dst_src[:2] - truth[:2])) > 0.5
    polished = motion_polish(q_seen, kf_seen, start, kf_twist)
    assert polished is not None
    assert np.hypot(*(polished.T_dst_src[:2] - truth[:2])) < 0.05
    assert abs(wrap_angle(float(polished.T_dst_src[2] - truth[2]))) < math.radians(0.05)
    # 4 m off at 30 m/s: more than max_shift_m (3 m) but less than a sweep's travel (7.5 m), so still reached
    far = motion_polish(q_seen, kf_seen, truth + np.array([4.0, 0.0, 0.0]), np.array([30.0, 0.0, 0.0]),
                        MotionConfig(radii_m=(5.0, 3.0, 2.0, 1.5, 1.0, 0.75, 0.6, 0.5, 0.4)))
    assert far is not None and np.hypot(*(far.T_dst_src[:2] - truth[:2])) < 1.0


@pytest.mark.parametrize("bad", [{"yaw_rate_sigma_radps": 1e-200}, {"speed_sigma_mps": 1e9}, {"iterations": 2000},
                                 {"sweep_period_s": 250.0}, {"num_azimuths": 10 ** 12}, {"min_associated": 100_000},
                                 {"radii_m": (60.0, 0.4)}, {"radii_m": (1.0,) * 40}, {"radii_m": (0.4, 0.75, 3.0)},
                                 {"radii_m": tuple(np.linspace(10, 0.4, 40))}, {"iterations": 34}])
def test_motion_settings_out_of_range_fail_at_construction(bad: dict) -> None:
    # accepted, each would have failed or slowed every answer instead (overflow of 1 / sigma^2, 290 ms fits)
    with pytest.raises(ConfigError):
        MotionConfig(**bad)


def test_odometry_twist_is_the_vehicles_motion_between_two_scans() -> None:
    # 0.25 s on a circle of radius 20 m at 8 m/s (0.4 rad/s); reversing; standing; implausible or unusable gaps
    th = 0.4 * 0.25
    arc = np.array([20 * math.sin(th), 20 * (1 - math.cos(th)), th])
    np.testing.assert_allclose(odometry_twist(arc, 0.25), [8.0, 0.0, 0.4], atol=1e-9)
    np.testing.assert_allclose(odometry_twist(np.array([-1.0, 0.0, 0.0]), 0.25), [-4.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_array_equal(odometry_twist(np.zeros(3), 0.25), np.zeros(3))
    for chord, dt in ((arc, 0.0), (arc, -0.25), (arc, 2.5), (np.array([50.0, 0.0, 0.0]), 0.25),
                      (np.array([np.nan, 0.0, 0.0]), 0.25), (arc, float("nan"))):
        assert odometry_twist(chord, dt) is None


def test_motion_polish_fits_a_reversing_vehicle_from_its_own_motion() -> None:
    # the map drive east at 10 m/s; the query reverses west at 4 m/s (facing east): the map drive's speed as the
    # prior is 14 m/s off, the vehicle's odometry says -4 m/s
    rng = np.random.default_rng(8)
    world = _street(rng)
    kf_twist = np.array([10.0, 0.0, 0.0])
    q_twist = np.array([-4.0, 0.0, 0.0])
    T_w_q = np.array([1.0, 0.5, 0.01])
    kf_seen = _seen_from(world, np.zeros(3), kf_twist)
    q_seen = _seen_from(world, T_w_q, q_twist) + rng.normal(scale=0.03, size=world.shape)
    truth = relative_pose(np.zeros(3), T_w_q)
    rigid = fit_rigid_2d(q_seen, kf_seen)
    guessed = motion_polish(q_seen, kf_seen, rigid, kf_twist)
    measured = motion_polish(q_seen, kf_seen, rigid, kf_twist, src_twist=q_twist)
    assert measured is not None
    assert np.hypot(*(measured.T_dst_src[:2] - truth[:2])) < 0.03
    np.testing.assert_allclose(measured.twist, q_twist, atol=0.3)
    guessed_err = math.inf if guessed is None else np.hypot(*(guessed.T_dst_src[:2] - truth[:2]))
    assert guessed_err > 2 * np.hypot(*(measured.T_dst_src[:2] - truth[:2]))
    assert motion_polish(q_seen, kf_seen, rigid, kf_twist, src_twist=np.array([np.nan, 0.0, 0.0])) is None


def test_motion_polish_keeps_the_rigid_pose_when_it_cannot_help() -> None:
    rng = np.random.default_rng(4)
    world = _street(rng, 8)
    seen = _seen_from(world, np.zeros(3), np.zeros(3))
    assert motion_polish(seen, seen, np.zeros(3), np.zeros(3)) is None  # fewer than min_associated landmarks
    world = _street(rng)
    seen = _seen_from(world, np.zeros(3), np.zeros(3))
    start = np.array([0.3, 0.0, 0.0])  # the rigid pose 0.3 m off: the fit corrects it, unless that moves it too far
    fixed = motion_polish(seen, seen, start, np.zeros(3))
    assert fixed is not None and np.hypot(*fixed.T_dst_src[:2]) < 0.01
    assert motion_polish(seen, seen, start, np.zeros(3), MotionConfig(max_shift_m=0.1)) is None
    with pytest.raises(ConfigError):
        MotionConfig(speed_sigma_mps=0.0)
    with pytest.raises(ConfigError):
        MotionConfig(radii_m=())
    with pytest.raises(ConfigError):
        MotionConfig(speed_sigma_mps=float("nan"))
    with pytest.raises(ConfigError):
        MotionConfig(max_shift_m=float("inf"))
    # a non-finite landmark keeps the rigid pose
    bad = seen.copy()
    bad[0, 0] = np.nan
    assert motion_polish(bad, seen, start, np.zeros(3)) is None


def test_localizer_answers_the_compensated_pose_and_the_same_decision() -> None:
    rng = np.random.default_rng(5)
    world = _street(rng, 900)
    # a map drive east at 10 m/s, a keyframe every 0.75 s (7.5 m)
    n = 6
    poses = np.column_stack([np.arange(n) * 7.5 - 20.0, np.zeros(n), np.zeros(n)])
    stamps = (np.arange(n) * 0.75e6).astype(np.int64)
    twist = np.array([10.0, 0.0, 0.0])

    def unit(x: np.ndarray) -> np.ndarray:
        return x / np.linalg.norm(x, axis=-1, keepdims=True)

    desc = unit(rng.normal(size=(len(world), 16)))  # one local descriptor per world landmark

    def features(T_w_s: np.ndarray, tw: np.ndarray, g: np.ndarray, ts: int) -> ScanFeatures:
        seen = _seen_from(world, T_w_s, tw)
        keep = np.hypot(seen[:, 0], seen[:, 1]) < 80.0
        return ScanFeatures(g, seen[keep], desc[keep], ts)

    g = unit(rng.normal(size=(n, 16)))
    kfs = [features(poses[i], twist, g[i], int(stamps[i])) for i in range(n)]
    loc = Localizer(GlobalIndex(g), InMemoryKeyframes(kfs, poses, stamps))
    T_w_q = np.array([poses[3, 0] + 1.5, 3.5, math.pi])  # driving the other way past keyframe 3
    query = features(T_w_q, np.array([9.0, 0.0, 0.0]), unit(g[3] + 0.05 * rng.normal(size=16)), 10**9)
    compensated = loc.localize(query)
    rigid = loc.localize(query, LocalizationConfig(motion=MotionConfig(enabled=False)))
    assert compensated.localized and rigid.localized
    assert compensated.motion_compensated and not rigid.motion_compensated
    assert compensated.best.keyframe_id == rigid.best.keyframe_id
    assert compensated.confidence == rigid.confidence and compensated.cues == rigid.cues
    np.testing.assert_allclose(compensated.T_map_query,
                               compose(poses[compensated.best.keyframe_id], compensated.best.T_keyframe_query))
    err = np.hypot(*(compensated.T_map_query[:2] - T_w_q[:2]))
    assert err < 0.1 < np.hypot(*(rigid.T_map_query[:2] - T_w_q[:2]))
    assert "motion_ms" in compensated.timings_ms
    # tracked from a prior whose odometry says how the vehicle moved: that motion is the fit's prior
    last = PosePrior(T_w_q - np.array([-2.25, 0.0, 0.0]), 0.5, math.radians(1.0), 10**9 - 250_000)
    prior = last.moved(np.array([2.25, 0.0, 0.0]), timestamp_us=10**9)  # 2.25 m in 0.25 s, heading west
    np.testing.assert_allclose(prior.twist, [9.0, 0.0, 0.0], atol=1e-9)
    tracked = loc.track(query, prior)
    assert tracked.mode == "tracking" and tracked.localized
    assert np.hypot(*(tracked.T_map_query[:2] - T_w_q[:2])) < 0.1
    assert last.moved(np.array([2.25, 0.0, 0.0])).twist is None  # no time: the map drive's speed
    # a vehicle reversing at 4 m/s (facing east, moving west) past keyframe 2: its odometry says so, the map drive's
    # 10 m/s forward does not; tracked with the scans' times it is fitted from its own motion
    T_w_r = np.array([poses[2, 0] + 1.0, -3.5, 0.0])
    reversing = features(T_w_r, np.array([-4.0, 0.0, 0.0]), unit(g[2] + 0.05 * rng.normal(size=16)), 2 * 10**9)
    before = PosePrior(T_w_r + np.array([1.0, 0.0, 0.0]), 0.5, math.radians(1.0), 2 * 10**9 - 250_000)
    timed = loc.track(reversing, before.moved(np.array([-1.0, 0.0, 0.0]), timestamp_us=2 * 10**9))
    untimed = loc.track(reversing, before.moved(np.array([-1.0, 0.0, 0.0])))
    assert timed.mode == untimed.mode == "tracking"
    err_timed = np.hypot(*(timed.T_map_query[:2] - T_w_r[:2]))
    err_untimed = np.hypot(*(untimed.T_map_query[:2] - T_w_r[:2]))
    assert err_timed < 0.05 and err_untimed > 2 * err_timed, (err_timed, err_untimed)
    with pytest.raises(ConfigError):
        PosePrior(T_w_q, 0.5, 0.1, twist=np.array([1.0, np.inf, 0.0]))
    # no drive's motion (QA session 40: 1e9 m/s was taken); a yaw rate in degrees per second is named
    for twist in ([1e9, 0.0, 0.0], [40.0, 50.0, 0.0], [10.0, 0.0, 30.0]):
        with pytest.raises(ConfigError, match="drive's"):
            PosePrior(T_w_q, 0.5, 0.1, twist=np.array(twist))
    assert PosePrior(T_w_q, 0.5, 0.1, twist=np.array([60.0, 0.0, -3.0])).twist is not None  # the limits themselves
    # a motion config allowing more than a prior takes: the odometry gives no twist rather than a refused prior
    fast = last.moved(np.array([25.0, 0.0, 0.0]), timestamp_us=10**9, motion_config=MotionConfig(max_speed_mps=500.0))
    assert fast.twist is None  # 100 m/s
    for stamp in (float("nan"), 1.7, 2**63, "12"):  # a scan time is a whole int64 of microseconds
        with pytest.raises(ConfigError):
            PosePrior(T_w_q, 0.5, 0.1, timestamp_us=stamp)  # type: ignore[arg-type]
    assert PosePrior(T_w_q, 0.5, 0.1, timestamp_us=np.int64(5)).timestamp_us == 5


def test_compiled_fit_agrees_with_the_numpy_path(monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("numba")
    rng = np.random.default_rng(6)
    world = _street(rng)
    kf_twist = np.array([8.0, 0.0, 0.1])
    kf_seen = _seen_from(world, np.zeros(3), kf_twist)
    q_seen = _seen_from(world, np.array([1.0, -2.0, math.pi - 0.02]), np.array([7.0, 0.1, -0.3]))
    q_seen += rng.normal(scale=0.03, size=q_seen.shape)
    start = fit_rigid_2d(q_seen, kf_seen)
    monkeypatch.setenv("RERADAR_JIT", "1")
    compiled = motion_polish(q_seen, kf_seen, start, kf_twist)
    monkeypatch.setenv("RERADAR_JIT", "0")
    plain = motion_polish(q_seen, kf_seen, start, kf_twist)
    assert compiled is not None and plain is not None
    assert compiled.num_associated == plain.num_associated
    np.testing.assert_allclose(compiled.T_dst_src, plain.T_dst_src, atol=1e-9)
    np.testing.assert_allclose(compiled.twist, plain.twist, atol=1e-7)
