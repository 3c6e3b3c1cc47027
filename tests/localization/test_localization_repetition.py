"""Place repetition: a keyframe of a street that repeats itself every 40 m is marked, one of an ordinary street is
not, and a global answer resting on a marked keyframe is ``ambiguous`` (``LocalizationConfig.max_place_repetition``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.se2 import compose, inverse, transform_points
from reradar_core.localization import InMemoryKeyframes, LocalizationConfig, Localizer, PosePrior
from reradar_core.localization.pipeline import REASON_AMBIGUOUS, Candidate
from reradar_core.localization.repetition import (
    PlaceRepetition,
    RepetitionTable,
    place_repetition,
    repetition_key,
    repetition_keyframes,
    repetition_settings,
)
from reradar_core.retrieval import GlobalIndex

PERIOD_M = 40.0
STREET_M = 400.0
SPACING_M = 6.0  # does not divide the period: the keyframes of two periods sit 2-4 m apart within it
RANGE_M = 60.0


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _world(periodic: bool, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(L, 2) landmarks along a 400 m street (metres, map frame) and their (L, 16) unit descriptors: one random
    40 m block repeated (``periodic``) or a new block every 40 m."""
    rng = np.random.default_rng(seed)
    pts, desc = [], []
    block = (rng.uniform([0.0, -40.0], [PERIOD_M, 40.0], (40, 2)), _unit(rng.normal(size=(40, 16))))
    for k in range(int(STREET_M / PERIOD_M) + 2):
        p, d = block if periodic else (rng.uniform([0.0, -40.0], [PERIOD_M, 40.0], (40, 2)),
                                       _unit(rng.normal(size=(40, 16))))
        pts.append(p + np.array([(k - 1) * PERIOD_M, 0.0]))
        desc.append(d)
    return np.concatenate(pts), np.concatenate(desc)


def _scan(world: tuple[np.ndarray, np.ndarray], T_map_sensor: np.ndarray, rng: np.random.Generator,
          frame: int, by_position: bool = False) -> ScanFeatures:
    """What a sensor at ``T_map_sensor`` sees of ``world`` within 60 m (landmarks in its frame, 5 cm noise); the
    global descriptor depends on the position within the period only, so rivals one period away are retrieved in
    both worlds alike (``by_position``: on the position along the street instead, a descriptor that ranks the
    keyframes of the same place first)."""
    pts, desc = world
    local = transform_points(inverse(T_map_sensor), pts)
    seen = np.hypot(*local.T) < RANGE_M
    phase = float(T_map_sensor[0]) / 100.0 if by_position else 2.0 * math.pi * float(T_map_sensor[0]) / PERIOD_M
    g = _unit(np.array([math.cos(phase), math.sin(phase), *np.full(14, 0.1)]))
    return ScanFeatures(g.astype(np.float32), local[seen] + rng.normal(scale=0.05, size=(int(seen.sum()), 2)),
                        desc[seen], frame)


def _localizer(periodic: bool, config: LocalizationConfig | None = None, spacing_m: float = SPACING_M,
               by_position: bool = False) -> tuple[Localizer, tuple]:
    world = _world(periodic)
    rng = np.random.default_rng(1)
    xs = np.arange(0.0, STREET_M + 1e-9, spacing_m)
    poses = np.column_stack([xs, np.zeros_like(xs), np.zeros_like(xs)])
    kfs = [_scan(world, p, rng, i, by_position) for i, p in enumerate(poses)]
    index = GlobalIndex(np.stack([f.global_descriptor for f in kfs]))
    return Localizer(index, InMemoryKeyframes(kfs, poses), config), world


def test_repetition_keyframes_are_the_nearest_of_its_place_and_the_retrieved_of_other_places() -> None:
    poses = np.array([[0.0, 0, 0], [5.0, 0, 0], [12.0, 0, 0], [19.0, 0, 0], [30.0, 0, 0], [100.0, 0, 0]])
    neighbours, rivals = repetition_keyframes(2, poses, [2, 5, 0, 4, 3], radius_m=20.0, max_neighbours=2)
    assert neighbours == [1, 3]  # both 7 m off (ties keep their order); keyframe 0 (12 m) is third
    assert rivals == [5]  # 88 m; keyframe 4 (18 m) and 0 (12 m) are its own place; itself is never a rival
    assert PlaceRepetition(0.0, 0.7, 5).ratio == 0.0  # no neighbour at its place: not judged
    assert PlaceRepetition(0.8, 0.6, 5).ratio == pytest.approx(0.75)


def test_a_keyframe_of_a_periodic_street_repeats_and_one_of_an_ordinary_street_does_not() -> None:
    periodic, _ = _localizer(True)
    ordinary, _ = _localizer(False)
    kid = 33  # 198 m: mid-street
    rep = periodic.place_repetition(kid)
    assert rep.ratio >= 1.0 and rep.rival_keyframe_id is not None
    offset = abs(periodic.keyframes.poses[rep.rival_keyframe_id][0] - periodic.keyframes.poses[kid][0])
    assert offset > 20.0 and min(offset % PERIOD_M, PERIOD_M - offset % PERIOD_M) <= SPACING_M / 2 + 1e-9
    assert periodic.place_repetition(kid) is rep  # cached
    plain = ordinary.place_repetition(kid)
    assert plain.neighbour_score > 0.5 and plain.ratio < 0.5  # keyframes down the road pose it where it is


def test_a_rival_below_the_answers_floor_does_not_count() -> None:
    """A rival is a place the scan could be answered at: one aligning less than the answers' floor is noise. The
    rival here is the place two periods on with every other landmark missing: it aligns about half of them."""
    world = _world(True)
    rng = np.random.default_rng(3)
    T_map_kf = np.array([198.0, 0.0, 0.0])
    kf = _scan(world, T_map_kf, rng, 0)
    T_map_near, T_map_far = np.array([204.0, 0.0, 0.0]), np.array([278.0, 0.0, 0.0])
    near = _scan(world, T_map_near, rng, 1)
    full = _scan(world, T_map_far, rng, 2)
    half = ScanFeatures(full.global_descriptor, full.keypoints_xy_m[::2], full.local_descriptors[::2], 2)

    def rep(floor: float) -> PlaceRepetition:
        return place_repetition(kf, T_map_kf, [Candidate(1, T_map_near, near, 0.0, 0)],
                                [Candidate(2, T_map_far, half, 0.0, 0)], LocalizationConfig(min_inlier_ratio=floor))

    low, high = rep(0.3), rep(0.7)
    assert 0.3 <= low.rival_score < 0.7 and low.rival_keyframe_id == 2 and low.neighbour_score > 0.8
    assert high.rival_score == 0.0 and high.rival_keyframe_id is None and high.ratio == 0.0
    assert high.neighbour_score == pytest.approx(low.neighbour_score)  # the reference needs no floor


def test_an_answer_on_a_repeated_place_is_ambiguous_and_one_on_an_ordinary_street_is_not() -> None:
    """The rule alone (tie margin off: here every period's keyframe screens alike, so the margin refuses too; on
    real maps the winner's keyframe can out-screen the true place's, 2-4 m off within the period)."""
    rng = np.random.default_rng(7)
    T_map_query = np.array([198.0, 1.0, math.radians(4.0)])  # at keyframe 33's position within the period
    no_margin = LocalizationConfig(min_place_margin=None)
    periodic, world = _localizer(True)
    query = _scan(world, T_map_query, rng, 99)
    unruled = periodic.localize(query, LocalizationConfig(min_place_margin=None, max_place_repetition=None))
    assert unruled.localized and unruled.T_map_query is not None  # on some period, by chance
    res = periodic.localize(query, no_margin)
    assert res.status == "not_localized" and res.reason == REASON_AMBIGUOUS and res.T_map_query is None
    assert res.best is not None and res.best.keyframe_id == unruled.best.keyframe_id
    assert periodic.place_repetition(res.best.keyframe_id, no_margin).ratio >= 0.95
    assert "repetition_ms" in res.timings_ms
    assert res.confidence == unruled.confidence  # the answer's cues are kept for diagnostics

    ordinary, world = _localizer(False)
    res = ordinary.localize(_scan(world, T_map_query, rng, 99))
    assert res.localized and res.T_map_query is not None and "repetition_ms" in res.timings_ms
    np.testing.assert_allclose(res.T_map_query[:2], T_map_query[:2], atol=0.3)


def test_a_tracked_answer_on_a_repeated_place_is_kept() -> None:
    """A pose prior tells the periods apart; the rule judges global answers only."""
    rng = np.random.default_rng(8)
    T_map_query = np.array([198.0, 1.0, math.radians(4.0)])
    periodic, world = _localizer(True)
    res = periodic.track(_scan(world, T_map_query, rng, 99), PosePrior(T_map_query + [0.5, -0.5, 0.01], 1.0, 0.03))
    assert res.mode == "tracking" and res.localized and res.T_map_query is not None
    np.testing.assert_allclose(res.T_map_query[:2], T_map_query[:2], atol=0.3)
    assert compose(inverse(res.T_map_query), T_map_query)[2] == pytest.approx(0.0, abs=math.radians(0.5))


def test_a_dense_map_whose_descriptor_ranks_its_own_place_first_is_still_judged() -> None:
    """Keyframes 1 m apart: the 40 within 20 m of a keyframe are retrieved before any other place, so the rivals
    are searched past them (review, session 27: the rule was silently off on such maps)."""
    dense, _ = _localizer(True, spacing_m=1.0, by_position=True)
    kid = 198
    ids, _ = dense.index.search(dense.index.vector(kid), 21)
    assert all(abs(dense.keyframes.poses[int(i)][0] - 198.0) <= 20.0 for i in ids[0])  # the 21 nearest: same place
    rep = dense.place_repetition(kid)
    assert rep.neighbour_score > 0.95 and rep.rival_score > 0.9 and rep.rival_keyframe_id is not None  # was 0, 0
    assert abs(dense.keyframes.poses[rep.rival_keyframe_id][0] - 198.0) > 20.0


def test_the_cached_repetition_is_reused_only_under_the_same_settings() -> None:
    periodic, _ = _localizer(True)
    rep = periodic.place_repetition(33)
    assert periodic.place_repetition(33, LocalizationConfig()) is rep
    for changed in (LocalizationConfig(min_inlier_ratio=0.9), LocalizationConfig(match_ratio=0.3),
                    LocalizationConfig(repetition_verify=1), LocalizationConfig(place_margin_radius_m=15.0)):
        assert repetition_key(changed) != repetition_key(LocalizationConfig())
        assert periodic.place_repetition(33, changed) is not rep  # computed again under those settings


def test_the_check_is_skipped_when_off_or_for_mutual_nn_and_kept_in_a_tracking_fallback() -> None:
    rng = np.random.default_rng(7)
    T_map_query = np.array([198.0, 1.0, math.radians(4.0)])
    periodic, world = _localizer(True)
    query = _scan(world, T_map_query, rng, 99)
    off = periodic.localize(query, LocalizationConfig(min_place_margin=None, max_place_repetition=None))
    assert off.localized and "repetition_ms" not in off.timings_ms
    mutual = periodic.localize(query, LocalizationConfig(pose_method="mutual_nn", min_place_margin=None))
    assert "repetition_ms" not in mutual.timings_ms  # the bar was chosen for the guided estimate only
    # a prior far from the scan: the tracking attempt fails and the global answer, refused, comes back as such
    far = PosePrior(np.array([20.0, 0.0, 0.0]), 1.0, 0.03)
    res = periodic.track(query, far, LocalizationConfig(min_place_margin=None))
    assert res.mode == "global" and res.tracking_lost and res.status == "not_localized"
    assert res.reason == REASON_AMBIGUOUS and res.best is not None and res.candidates and res.cues is not None


def test_the_check_applies_to_guided_answers_with_a_bar_only() -> None:
    assert LocalizationConfig().checks_place_repetition
    assert not LocalizationConfig(max_place_repetition=None).checks_place_repetition
    assert not LocalizationConfig(pose_method="mutual_nn").checks_place_repetition


def test_the_fit_collects_its_runs_with_the_check_off() -> None:
    """``reradar fit-confidence`` labels every answer; the check is chosen on such runs, never applied to them."""
    from reradar_core.localization.confidence_fit import PROBE_FLOOR, PROBE_PLACE_MARGIN, collection_config

    config = collection_config()
    assert config.max_place_repetition is None and config.min_confidence == 0.0
    assert config.min_inlier_ratio == PROBE_FLOOR and config.min_place_margin == PROBE_PLACE_MARGIN


@pytest.mark.parametrize("kwargs", [{"max_place_repetition": 0.0}, {"repetition_rivals": 0},
                                    {"repetition_neighbours": 0}, {"repetition_verify": 0}])
def test_repetition_settings_are_checked(kwargs: dict) -> None:
    with pytest.raises(ConfigError):
        LocalizationConfig(**kwargs)


def test_a_whole_map_table_is_every_keyframes_repetition_with_any_number_of_threads() -> None:
    periodic, _ = _localizer(True)
    one = periodic.place_repetitions(workers=1)
    fresh, _ = _localizer(True)
    done: list[tuple[int, int]] = []
    two = fresh.place_repetitions(workers=2, progress=lambda d, t: done.append((d, t)))
    n = len(periodic)
    assert len(one) == n and done[-1] == (n, n) and len(done) == n
    for a in ("neighbour_score", "rival_score", "rival_keyframe_id"):
        np.testing.assert_array_equal(getattr(one, a), getattr(two, a))
    for kid in (0, 33, n - 1):
        assert one.at(kid) == periodic.place_repetition(kid)
    assert one.settings == repetition_settings(LocalizationConfig())
    # mid-street keyframes of a periodic street repeat (the ends see part of the street only)
    assert (one.ratios[10:-10] >= 0.95).mean() > 0.9
    plain = _localizer(False)[0].place_repetitions()
    assert (plain.ratios >= 0.95).sum() == 0


def test_an_adopted_table_is_what_the_check_reads_under_its_settings_only() -> None:
    rng = np.random.default_rng(7)
    T_map_query = np.array([198.0, 1.0, math.radians(4.0)])
    no_margin = LocalizationConfig(min_place_margin=None)
    periodic, world = _localizer(True, no_margin)
    query = _scan(world, T_map_query, rng, 99)
    measured = periodic.place_repetitions()
    # a fresh localizer answering from the table gives the answer it would measure
    fresh, _ = _localizer(True, no_margin)
    assert fresh.adopt_repetitions(measured)
    res = fresh.localize(query)
    assert res.status == "not_localized" and res.reason == REASON_AMBIGUOUS
    # the table is read, not re-measured: one that marks nothing lets the same answer through
    n = len(periodic)
    blank = RepetitionTable(measured.settings, np.ones(n), np.zeros(n), np.full(n, -1))
    trusting, _ = _localizer(True, no_margin)
    assert trusting.adopt_repetitions(blank)
    assert trusting.localize(query).localized
    # another setting's (or another map size's) table is not taken: the keyframe is measured as it wins
    other, _ = _localizer(True, no_margin)
    assert not other.adopt_repetitions(RepetitionTable(repetition_settings(LocalizationConfig(repetition_verify=1)),
                                                       np.ones(n), np.zeros(n), np.full(n, -1)))
    assert not other.adopt_repetitions(RepetitionTable(measured.settings, np.ones(3), np.zeros(3), np.full(3, -1)))
    assert other.localize(query).reason == REASON_AMBIGUOUS


def test_repetition_settings_are_canonical_json_of_every_setting_read() -> None:
    import json

    base = repetition_settings(LocalizationConfig())
    named = json.loads(base)
    assert base == repetition_settings(LocalizationConfig()) and named["version"] == 1
    assert named["place_margin_radius_m"] == 20.0 and named["repetition_rivals"] == 20 and "alignment" in named
    from reradar_core.matching import AlignmentConfig

    # a number is a number: 20 and 20.0 are one setting (QA: an int blocked a stored table's adoption)
    assert repetition_settings(LocalizationConfig(place_margin_radius_m=20)) == base
    for changed in (LocalizationConfig(repetition_rivals=5), LocalizationConfig(min_inlier_ratio=0.9),
                    LocalizationConfig(alignment=AlignmentConfig(score_threshold_m=1.0))):
        assert repetition_settings(changed) != base


@pytest.mark.parametrize("arrays, match", [
    (([0.5, 0.5], [0.2], [-1, -1]), "one length"),
    (([0.5, 1.5], [0.0, 0.0], [-1, -1]), "neighbour scores"),
    (([0.5, 0.5], [np.nan, 0.0], [-1, -1]), "rival scores"),
    (([0.5, 0.5], [0.4, 0.0], [1, 2]), r"\[-1, 2\)"),
    (([0.5, 0.5], [0.4, 0.0], [0, -1]), "differ from their own"),
    (([0.5, 0.5], [0.4, 0.0], [-1, -1]), "needs a rival score"),
    (([0.5, 0.5], [0.0, 0.0], [0.5, -1.0]), "integers"),
    (([0.5, 0.5], [0.0, 0.0], np.array([2**64 - 1, 2**64 - 1], np.uint64)), "fit in int64"),  # would wrap to -1
])
def test_a_table_that_cannot_be_a_measure_is_refused(arrays: tuple, match: str) -> None:
    n, r, i = (np.asarray(a) for a in arrays)
    with pytest.raises(ConfigError, match=match):
        RepetitionTable("{}", n, r, i)


def test_a_whole_map_pass_stopped_by_its_progress_callback_stops_measuring() -> None:
    """A cancelled build raises from the progress callback: the keyframes not yet begun are not measured."""
    periodic, _ = _localizer(True)
    measured: list[int] = []
    measure = periodic.place_repetition

    def counting(keyframe_id: int, config: LocalizationConfig | None = None) -> PlaceRepetition:
        measured.append(keyframe_id)
        return measure(keyframe_id, config)

    periodic.place_repetition = counting  # type: ignore[method-assign]

    def stop(done: int, total: int) -> None:
        if done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        periodic.place_repetitions(workers=2, progress=stop)
    assert 3 <= len(measured) < len(periodic) // 2
