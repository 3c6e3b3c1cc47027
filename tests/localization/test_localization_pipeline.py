"""Localization over synthetic ScanFeatures: known transforms recovered, unknown places rejected."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.se2 import compose, inverse, transform_points, wrap_angle
from reradar_core.localization import (
    REASON_NO_CANDIDATE,
    REASON_SCREENED_OUT,
    REASON_TOO_FEW_INLIERS,
    CachedKeyframe,
    Candidate,
    LocalizationConfig,
    localize,
)
from reradar_core.matching import AlignmentConfig


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _keyframe(rng: np.random.Generator, n: int = 120, c: int = 32, ts: int = 0) -> ScanFeatures:
    kps = rng.uniform(-60, 60, size=(n, 2))
    return ScanFeatures(_unit(rng.normal(size=16)), kps, _unit(rng.normal(size=(n, c))), ts)


def _query_from(kf: ScanFeatures, T_kf_query: np.ndarray, rng: np.random.Generator, keep: float = 0.7,
                noise_m: float = 0.1, outliers: int = 30) -> ScanFeatures:
    """The keyframe's landmarks seen from pose T_kf_query: p_query = inverse(T_kf_query) * p_kf."""
    n = kf.keypoints_xy_m.shape[0]
    sel = np.sort(rng.choice(n, int(keep * n), replace=False))
    pts = transform_points(inverse(T_kf_query), kf.keypoints_xy_m[sel].astype(np.float64))
    pts += rng.normal(scale=noise_m, size=pts.shape)
    desc = kf.local_descriptors[sel].astype(np.float32) + rng.normal(scale=0.05, size=(len(sel), kf.local_descriptors.shape[1]))
    out_pts = rng.uniform(-60, 60, size=(outliers, 2))
    out_desc = rng.normal(size=(outliers, desc.shape[1]))
    return ScanFeatures(kf.global_descriptor, np.vstack([pts, out_pts]), _unit(np.vstack([desc, out_desc])), 99)


def _candidates(kfs: list[ScanFeatures], poses: np.ndarray, order: list[int]) -> list[Candidate]:
    return [Candidate(i, poses[i], kfs[i], 0.1 * r, r) for r, i in enumerate(order)]


def test_known_transform_recovered_and_absolute_pose_composed() -> None:
    rng = np.random.default_rng(0)
    kfs = [_keyframe(rng, ts=1000 * i) for i in range(5)]
    poses = np.column_stack([np.arange(5) * 50.0, np.zeros(5) + 10.0, np.linspace(0, 1, 5)])
    T_kf_query = np.array([4.0, -2.5, np.deg2rad(25.0)])
    query = _query_from(kfs[2], T_kf_query, rng)
    res = localize(query, _candidates(kfs, poses, [2, 0, 1, 3, 4]))
    assert res.status == "localized" and res.reason is None
    assert res.best is not None and res.best.keyframe_id == 2
    assert res.best.T_keyframe_query is not None
    np.testing.assert_allclose(res.best.T_keyframe_query[:2], T_kf_query[:2], atol=0.1)
    assert abs(wrap_angle(res.best.T_keyframe_query[2] - T_kf_query[2])) < np.deg2rad(0.5)
    expected = compose(poses[2], T_kf_query)
    assert res.T_map_query is not None
    np.testing.assert_allclose(res.T_map_query[:2], expected[:2], atol=0.15)
    assert res.best.num_inliers >= 70 and 0 < res.best.inlier_ratio <= 1
    assert len(res.candidates) == 5


def test_geometric_reranking_picks_true_keyframe_over_wrong_top1() -> None:
    rng = np.random.default_rng(1)
    kfs = [_keyframe(rng) for _ in range(4)]
    poses = np.zeros((4, 3))
    poses[:, 0] = [0, 100, 200, 300]
    query = _query_from(kfs[3], np.array([1.0, 1.0, 0.3]), rng)
    order = [0, 1, 3, 2]  # retrieval put the true keyframe at rank 2
    reranked = localize(query, _candidates(kfs, poses, order), LocalizationConfig(top_k=5))
    assert reranked.localized and reranked.best is not None
    assert reranked.best.keyframe_id == 3 and reranked.best.rank == 2
    plain = localize(query, _candidates(kfs, poses, order), LocalizationConfig(rerank=False))
    assert plain.status == "not_localized" and plain.reason == REASON_TOO_FEW_INLIERS
    assert plain.best is not None and plain.best.keyframe_id == 0


def test_screen_keeps_true_keyframe_from_deep_in_the_retrieval_list() -> None:
    """12 candidates, the true one at rank 9: the alignment screen must pass it to full verification (3)."""
    rng = np.random.default_rng(5)
    kfs = [_keyframe(rng, ts=i) for i in range(12)]
    poses = np.column_stack([np.arange(12) * 40.0, np.zeros(12), np.zeros(12)])
    T_kf_query = np.array([-3.0, 2.0, np.deg2rad(-140.0)])
    query = _query_from(kfs[7], T_kf_query, rng)
    order = [0, 1, 2, 3, 4, 5, 6, 8, 9, 7, 10, 11]
    res = localize(query, _candidates(kfs, poses, order), LocalizationConfig(top_k=12, verify_k=3,
                                                                           stop_verify_ratio=None))
    assert res.localized and res.best is not None and res.best.keyframe_id == 7 and res.best.rank == 9
    assert res.T_map_query is not None
    np.testing.assert_allclose(res.T_map_query[:2], compose(poses[7], T_kf_query)[:2], atol=0.15)
    assert len(res.candidates) == 12 and [c.rank for c in res.candidates] == list(range(12))
    screened_out = [c for c in res.candidates if c.reason == REASON_SCREENED_OUT]
    assert len(screened_out) == 9 and all(c.num_inliers == 0 for c in screened_out)
    scores = {c.keyframe_id: c.screen_score for c in res.candidates}
    assert all(v is not None for v in scores.values())
    assert scores[7] == max(scores.values()) and scores[7] > 0.5
    assert "screen_ms" in res.timings_ms


def test_unknown_place_is_not_localized() -> None:
    rng = np.random.default_rng(2)
    kfs = [_keyframe(rng) for _ in range(5)]
    poses = np.zeros((5, 3))
    unknown = _keyframe(rng)  # a place that is not in the map
    res = localize(unknown, _candidates(kfs, poses, [0, 1, 2, 3, 4]))
    assert res.status == "not_localized"
    assert res.reason == REASON_TOO_FEW_INLIERS
    assert res.T_map_query is None
    assert res.best is not None and res.best.num_inliers < LocalizationConfig().min_inliers


def test_no_candidates_and_empty_query() -> None:
    rng = np.random.default_rng(3)
    res = localize(_keyframe(rng), [])
    assert res.status == "not_localized" and res.reason == REASON_NO_CANDIDATE and res.best is None
    empty = ScanFeatures(_unit(rng.normal(size=16)), np.zeros((0, 2)), np.zeros((0, 32)), 0)
    res = localize(empty, _candidates([_keyframe(rng)], np.zeros((1, 3)), [0]))
    assert res.status == "not_localized" and res.best is not None and res.best.num_matches == 0


def test_top_k_limits_verified_candidates() -> None:
    rng = np.random.default_rng(4)
    kfs = [_keyframe(rng) for _ in range(6)]
    query = _query_from(kfs[5], np.array([0.0, 0.0, 0.0]), rng)
    res = localize(query, _candidates(kfs, np.zeros((6, 3)), list(range(6))), LocalizationConfig(top_k=3, verify_k=3))
    assert len(res.candidates) == 3 and res.status == "not_localized"


@pytest.mark.parametrize("kwargs", [{"top_k": 0}, {"min_inliers": 1}, {"min_inlier_ratio": 1.5}])
def test_config_validation(kwargs: dict) -> None:
    with pytest.raises(ConfigError):
        LocalizationConfig(**kwargs)


def _true_keyframe_at_rank_25() -> tuple[list[ScanFeatures], np.ndarray, np.ndarray, ScanFeatures, list[int]]:
    """40 keyframes 50 m apart, a query seen from keyframe 33 and a retrieval order that ranks it 25th:
    (keyframes, poses, T_kf_query, query, order)."""
    rng = np.random.default_rng(7)
    kfs = [_keyframe(rng, ts=i) for i in range(40)]
    poses = np.column_stack([np.arange(40) * 50.0, np.zeros(40), np.zeros(40)])
    T_kf_query = np.array([2.0, -1.0, np.deg2rad(60.0)])
    query = _query_from(kfs[33], T_kf_query, rng)
    order = [i for i in range(40) if i != 33]
    order.insert(25, 33)
    return kfs, poses, T_kf_query, query, order


def test_expansion_screens_further_only_when_no_candidate_aligns() -> None:
    """True keyframe at rank 25: screening 10 finds nothing good, so the rest up to ``max_candidates`` is
    screened in one round (lazily loaded), or in blocks of ``expansion_block`` until one aligns well; with the
    expansion disabled the query is not localized. A confident query loads only 10."""
    kfs, poses, T_kf_query, query, order = _true_keyframe_at_rank_25()
    loaded: list[int] = []

    def lazy(order_: list[int]) -> list[Candidate]:
        def loader(i: int):
            def load():
                loaded.append(i)
                return CachedKeyframe(kfs[i], AlignmentConfig())
            return load
        return [Candidate(i, poses[i], None, 0.1 * r, r, loader=loader(i)) for r, i in enumerate(order_)]

    cfg = LocalizationConfig(top_k=10, verify_k=2, max_candidates=40)
    assert cfg.num_to_retrieve == 40
    res = localize(query, lazy(order), cfg)
    assert res.localized and res.best is not None and res.best.keyframe_id == 33 and res.best.rank == 25
    assert len(res.candidates) == 40 and len(loaded) == 40  # 10, then the other 30 in one round
    np.testing.assert_allclose(res.T_map_query[:2], compose(poses[33], T_kf_query)[:2], atol=0.15)

    loaded.clear()
    blocks = localize(query, lazy(order), LocalizationConfig(top_k=10, verify_k=2, max_candidates=40,
                                                             expansion_block=10))
    assert blocks.localized and blocks.best is not None and blocks.best.keyframe_id == 33
    assert len(blocks.candidates) == 30 and len(loaded) == 30  # three blocks of 10 screened, the rest never read

    off = localize(query, lazy(order), LocalizationConfig(top_k=10, verify_k=2, max_candidates=10))
    assert off.status == "not_localized" and len(off.candidates) == 10

    loaded.clear()
    confident = localize(query, lazy([33] + order[:25] + order[26:]), cfg)
    assert confident.localized and confident.best.keyframe_id == 33 and len(loaded) == 10


def test_prescreen_keeps_the_best_of_a_deep_round_for_the_full_screen() -> None:
    """True keyframe at rank 25 of 40: with ``prescreen_keep`` the 30 candidates of the deeper round get the
    coarse screen's scores (``prescreen_alignment``: fewer source landmarks and minimal sets), and only the best 5
    of them the full screen; the true keyframe is among those and is found, with the full screen's score. The
    first ``top_k`` are screened in full either way; a round no larger than ``prescreen_keep`` is screened in
    full directly."""
    from reradar_core.localization.screening import screen_candidates

    kfs, poses, T_kf_query, query, order = _true_keyframe_at_rank_25()
    cfg = LocalizationConfig(top_k=10, verify_k=2, max_candidates=40, prescreen_keep=5)
    res = localize(query, _candidates(kfs, poses, order), cfg)
    assert res.localized and res.best is not None and res.best.keyframe_id == 33 and res.best.rank == 25
    np.testing.assert_allclose(res.T_map_query[:2], compose(poses[33], T_kf_query)[:2], atol=0.15)
    assert len(res.candidates) == 40 and all(c.screen_score is not None for c in res.candidates)

    def scores(ranks: list[int], alignment: AlignmentConfig) -> np.ndarray:
        cands = _candidates(kfs, poses, order)
        return screen_candidates(query.keypoints_xy_m, query.local_descriptors,
                                 [cands[r].screen_data(cfg.alignment) for r in ranks], alignment)

    got = {c.rank: c.screen_score for c in res.candidates}
    deep = list(range(10, 40))
    coarse = scores(deep, cfg.prescreen_alignment)
    kept = sorted(deep, key=lambda r: (-coarse[r - 10], r))[:5]
    assert 25 in kept
    full = scores(kept, cfg.alignment)
    assert [got[r] for r in kept] == full.tolist()  # the full screen's numbers for the kept five
    assert [got[r] for r in deep if r not in kept] == [coarse[r - 10] for r in deep if r not in kept]
    assert [got[r] for r in range(10)] == scores(list(range(10)), cfg.alignment).tolist()
    assert cfg.prescreen_alignment.screen_source_points == 64 and cfg.prescreen_alignment.screen_hypotheses == 1000

    # a round of at most ``prescreen_keep`` candidates: the full screen only
    small = localize(query, _candidates(kfs, poses, order), LocalizationConfig(
        top_k=10, verify_k=2, max_candidates=40, expansion_block=10, prescreen_keep=10))
    assert small.localized and small.best.keyframe_id == 33
    got = {c.rank: c.screen_score for c in small.candidates}
    assert [got[r] for r in range(20, 30)] == scores(list(range(20, 30)), cfg.alignment).tolist()
    with pytest.raises(ConfigError):
        LocalizationConfig(prescreen_keep=0)
    with pytest.raises(ConfigError):
        LocalizationConfig(prescreen_source_points=1)


def test_a_refused_answer_screens_further() -> None:
    """A decoy at rank 0 (an alias holding 75 % of the true keyframe's landmarks, at another place) screens well
    enough to stop the score-based expansion but is refused by the floor; the true keyframe at rank 25 is then
    found by screening deeper (``expand_on_refusal``): by default all the rest up to ``max_candidates`` in one
    round, with ``refusal_block`` in blocks of that size (stopping at the block that localizes). Without it the
    query is refused after 10."""
    rng = np.random.default_rng(11)
    kfs = [_keyframe(rng, ts=i) for i in range(40)]
    poses = np.column_stack([np.arange(40) * 50.0, np.zeros(40), np.zeros(40)])
    true = kfs[33]
    keep = rng.permutation(len(true.keypoints_xy_m)) < int(0.75 * len(true.keypoints_xy_m))
    kps = np.where(keep[:, None], true.keypoints_xy_m, rng.uniform(-60, 60, size=true.keypoints_xy_m.shape))
    kfs[5] = ScanFeatures(kfs[5].global_descriptor, kps, true.local_descriptors, 5)
    T_kf_query = np.array([2.0, -1.0, np.deg2rad(30.0)])
    query = _query_from(true, T_kf_query, rng)
    order = [5] + [i for i in range(40) if i not in (5, 33)]
    order.insert(25, 33)
    base = {"top_k": 10, "verify_k": 2, "max_candidates": 40, "expand_below_screen_score": 0.4,
            "min_inlier_ratio": 0.65, "min_confidence": 0.0}
    res = localize(query, _candidates(kfs, poses, order), LocalizationConfig(**base))
    decoy = next(c for c in res.candidates if c.keyframe_id == 5)
    assert decoy.screen_score is not None and decoy.screen_score >= 0.4 and decoy.inlier_ratio < 0.65
    assert res.localized and res.best is not None and res.best.keyframe_id == 33 and res.best.rank == 25
    assert len(res.candidates) == 40  # one deeper round: every retrieved candidate up to max_candidates
    np.testing.assert_allclose(res.T_map_query[:2], compose(poses[33], T_kf_query)[:2], atol=0.15)
    blocks = localize(query, _candidates(kfs, poses, order), LocalizationConfig(**base, expansion_block=10))
    assert blocks.localized and blocks.best is not None and blocks.best.keyframe_id == 33
    assert len(blocks.candidates) == 30  # two more blocks of 10 screened after the refusal, not all 40
    np.testing.assert_array_equal(blocks.T_map_query, res.T_map_query)
    off = localize(query, _candidates(kfs, poses, order), LocalizationConfig(**base, expand_on_refusal=False))
    assert off.status == "not_localized" and len(off.candidates) == 10 and off.best.keyframe_id == 5
    with pytest.raises(ConfigError):
        LocalizationConfig(expansion_block=0)


def test_verification_stops_once_an_answer_is_confident() -> None:
    """Two true keyframes at ranks 3 and 6 screen best: with a stop ratio of 0.5 only the best-screened one
    is verified; without it all ``verify_k`` are, and the answer is the same place."""
    rng = np.random.default_rng(8)
    kfs = [_keyframe(rng, ts=i) for i in range(10)]
    kfs[6] = ScanFeatures(kfs[6].global_descriptor, kfs[3].keypoints_xy_m, kfs[3].local_descriptors, 6)
    poses = np.column_stack([np.arange(10) * 40.0, np.zeros(10), np.zeros(10)])
    poses[6] = poses[3]
    query = _query_from(kfs[3], np.array([1.0, 2.0, 0.4]), rng)
    order = list(range(10))
    fast = localize(query, _candidates(kfs, poses, order), LocalizationConfig(top_k=10, verify_k=3,
                                                                            stop_verify_ratio=0.5))
    full = localize(query, _candidates(kfs, poses, order), LocalizationConfig(top_k=10, verify_k=3,
                                                                            stop_verify_ratio=None))
    assert sum(c.reason != REASON_SCREENED_OUT for c in fast.candidates) == 1
    assert sum(c.reason != REASON_SCREENED_OUT for c in full.candidates) == 3
    assert fast.localized and full.localized and fast.best.keyframe_id in (3, 6)
    np.testing.assert_allclose(fast.T_map_query, full.T_map_query, atol=0.05)
    with pytest.raises(ConfigError):
        LocalizationConfig(stop_verify_ratio=1.5)


def test_periodic_place_is_not_localized_as_ambiguous() -> None:
    # a lattice of identical posts (one shared descriptor): every one-period shift aligns as many landmarks,
    # so the answer is refused as ambiguous rather than guessed
    from reradar_core.localization import REASON_AMBIGUOUS

    g = np.arange(-48.0, 49.0, 8.0)
    pts = np.array([(x, y) for x in g for y in g])
    desc = np.ones((len(pts), 8)) / np.sqrt(8)
    kf = ScanFeatures(_unit(np.ones(16)), pts, desc, 0)
    query = ScanFeatures(kf.global_descriptor, transform_points(inverse(np.array([1.0, 0.5, 0.0])), pts), desc, 1)
    cfg = LocalizationConfig(alignment=AlignmentConfig(top_k_matches=8))
    res = localize(query, _candidates([kf], np.zeros((1, 3)), [0]), cfg)
    assert res.status == "not_localized" and res.reason == REASON_AMBIGUOUS


def test_a_tie_in_the_screen_whose_pose_disagrees_is_verified_too() -> None:
    """QA (session 24): two keyframes 10 m apart screened alike, the first in order was verified alone and its
    answer, 10 m off along the road, passed (confidence 0.9998). Here keyframe 0 (retrieval rank 0) holds 100 of the
    query's landmarks as seen from its own origin plus 23 more 1 m off (they count in the 1.5 m screen, not as 0.75 m
    inliers): it screens best and answers 10 m off with 100 inliers. Keyframe 1, 10 m away, holds 120 of them as seen
    from the truth: it screens within the 2 % margin, and the first answer seen from it aligns few landmarks, so it is
    verified too and wins with 120 inliers. A tie that agrees with the answer costs no verification."""
    rng = np.random.default_rng(11)
    q_pts = rng.uniform(-60, 60, size=(150, 2))
    desc = _unit(rng.normal(size=(150, 32)))
    ang = rng.uniform(0, 2 * np.pi, 23)
    off = q_pts[100:123] + np.column_stack([np.cos(ang), np.sin(ang)])
    decoy = ScanFeatures(_unit(rng.normal(size=16)), np.vstack([q_pts[:100], off]), desc[:123].astype(np.float32), 0)
    truth = ScanFeatures(_unit(rng.normal(size=16)), q_pts[30:], desc[30:].astype(np.float32), 1)
    poses = np.array([[10.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    query = ScanFeatures(decoy.global_descriptor, q_pts + rng.normal(scale=0.02, size=q_pts.shape), desc, 99)
    cfg = LocalizationConfig(min_confidence=0.0, stop_verify_ratio=0.9)
    res = localize(query, _candidates([decoy, truth], poses, [0, 1]), cfg)
    screen = {c.keyframe_id: c.screen_score for c in res.candidates}
    assert screen[0] >= screen[1] >= screen[0] - 0.02  # a tie, the decoy first
    assert res.localized and res.best.keyframe_id == 1 and res.best.num_inliers >= 115
    np.testing.assert_allclose(res.T_map_query[:2], [0.0, 0.0], atol=0.2)
    alone = localize(query, _candidates([decoy, truth], poses, [0, 1]),
                     LocalizationConfig(min_confidence=0.0, stop_verify_ratio=0.9, verify_ties=0))
    assert alone.best.keyframe_id == 0 and abs(alone.T_map_query[0] - 10.0) < 0.5  # before: 10 m off
    with pytest.raises(ConfigError):
        LocalizationConfig(verify_ties=-1)


def test_a_refusal_below_the_floor_is_too_few_inliers_not_ambiguous():
    """QA session 38: answers aligning 20-30 % of their landmarks (below the 45 % floor) read ``ambiguous``."""
    from types import SimpleNamespace

    from reradar_core.localization.pipeline import LocalizationConfig, _refusal_reason

    cfg = LocalizationConfig()
    floor = cfg.effective_min_inlier_ratio

    def best(reason, n, ratio):
        return SimpleNamespace(reason=reason, num_inliers=n, inlier_ratio=ratio)

    assert _refusal_reason(best("ambiguous", 153, 0.299), cfg) == "too_few_inliers"
    assert _refusal_reason(best("ambiguous", 300, floor + 0.05), cfg) == "ambiguous"
    assert _refusal_reason(best("too_few_matches", 3, 0.01), cfg) == "too_few_matches"
    assert _refusal_reason(best(None, 5, 0.9), cfg) == "too_few_inliers"
