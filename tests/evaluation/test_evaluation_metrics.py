"""Metrics on small hand-computed cases (paper, Sec. Evaluation Metrics)."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.errors import ConfigError
from reradar_core.evaluation import (
    RADIUS_M,
    f1_max,
    has_revisit,
    localization_errors,
    precision_recall_curve,
    radius_for,
    recall_at_1,
    retrieval_correct,
    rotation_success_rate,
    success_rate,
    summarize,
)


def test_recall_at_1_counts_all_queries():
    query = np.zeros((5, 2))
    # top-1 at 5 m, 25 m, 19.9 m, exactly 20 m, and nothing retrieved (NaN)
    retrieved = np.array([[5.0, 0.0], [0.0, 25.0], [-19.9, 0.0], [12.0, 16.0], [np.nan, np.nan]])
    np.testing.assert_array_equal(retrieval_correct(query, retrieved, 20.0), [True, False, True, True, False])
    assert recall_at_1(query, retrieved, 20.0) == pytest.approx(3 / 5)
    assert recall_at_1(query, retrieved, 25.0) == pytest.approx(4 / 5)
    assert recall_at_1(np.zeros((0, 2)), np.zeros((0, 2)), 20.0) == 0.0


def test_f1_max_hand_computed():
    # distance: 0.1  0.2  0.3  0.4  0.5
    # correct:   T    F    T    F    F
    # revisit:   T    T    T    F    T
    # delta=0.1: accept {0}:        TP=1 FP=0, reject {1,2,3,4}: FN=3 (1,2,4)  P=1    R=1/4  F1=0.4
    # delta=0.2: accept {0,1}:      TP=1 FP=1, reject {2,3,4}:   FN=2          P=1/2  R=1/3  F1=0.4
    # delta=0.3: accept {0,1,2}:    TP=2 FP=1, reject {3,4}:     FN=1          P=2/3  R=2/3  F1=2/3
    # delta=0.4: accept {0..3}:     TP=2 FP=2, reject {4}:       FN=1          P=1/2  R=2/3  F1=4/7
    # delta=0.5: accept all:        TP=2 FP=3,                   FN=0          P=2/5  R=1    F1=4/7
    d = np.array([0.3, 0.1, 0.5, 0.2, 0.4])  # shuffled: the function must sort
    correct = np.array([True, True, False, False, False])
    revisit = np.array([True, True, True, True, False])
    f1, p, r, thr = f1_max(d, correct, revisit)
    assert f1 == pytest.approx(2 / 3)
    np.testing.assert_allclose(thr, [0.1, 0.2, 0.3, 0.4, 0.5])
    np.testing.assert_allclose(p, [1, 1 / 2, 2 / 3, 1 / 2, 2 / 5])
    np.testing.assert_allclose(r, [1 / 4, 1 / 3, 2 / 3, 2 / 3, 1])


def test_f1_max_ties_and_infinite_distances():
    # ties are accepted together: delta=0.1 -> TP=1 FP=1 FN=1 (P=R=1/2, F1=1/2); delta=0.2 -> TP=2 FP=1 FN=0
    # (P=2/3, R=1, F1=4/5)
    f1, p, r, thr = f1_max([0.1, 0.1, 0.2], [True, False, True], [True, True, True])
    assert f1 == pytest.approx(0.8)
    np.testing.assert_allclose(thr, [0.1, 0.2])
    np.testing.assert_allclose(p, [0.5, 2 / 3])
    # +inf = no candidate, never accepted: TP=1 FP=0 FN=1 -> P=1, R=1/2, F1=2/3
    f1_inf, _, _, thr_inf = f1_max([0.1, np.inf], [True, False], [True, True])
    assert f1_inf == pytest.approx(2 / 3) and thr_inf.tolist() == [0.1]


def test_f1_max_degenerate_cases():
    assert f1_max([0.5, 0.7], [False, False], [False, False])[0] == 0.0  # nothing correct
    assert f1_max([], [], [])[0] == 0.0
    # no revisits at all, but correct accepted queries are impossible then; all accepted are FP
    assert f1_max([0.1], [False], [False])[0] == 0.0
    assert precision_recall_curve([0.2, 0.1], [True, True], [True, True]).f1_max == 1.0
    with pytest.raises(ValueError, match="NaN"):
        f1_max([np.nan], [True], [True])
    with pytest.raises(ValueError, match="differ"):
        f1_max([0.1, 0.2], [True], [True, True])


def test_has_revisit():
    db = np.array([[0.0, 0.0], [100.0, 0.0]])
    q = np.array([[10.0, 0.0], [50.0, 0.0], [100.0, 24.0], [100.0, 26.0]])
    np.testing.assert_array_equal(has_revisit(q, db, 25.0), [True, False, True, False])
    assert has_revisit(q, np.zeros((0, 2)), 25.0).tolist() == [False] * 4


def test_localization_errors_and_success():
    est = np.array([[0, 0, 0], [3, 4, np.radians(170)], [10, 0, np.radians(-172)], [np.nan] * 3], float)
    gt = np.array([[0, 0, np.radians(5)], [0, 0, np.radians(-175)], [0, 0, np.radians(175)], [0, 0, 0]], float)
    e_t, e_r = localization_errors(est, gt)
    np.testing.assert_allclose(e_t[:3], [0.0, 5.0, 10.0])
    np.testing.assert_allclose(e_r[:3], [5.0, 15.0, 13.0], atol=1e-9)  # heading errors wrap across +-180
    assert np.isnan(e_t[3]) and np.isnan(e_r[3])
    # success needs e_t < R and e_r < 10 deg jointly: only query 0; the failed query 3 stays in the denominator
    assert success_rate(e_t, e_r, 20.0) == pytest.approx(1 / 4)
    assert success_rate(e_t, e_r, 20.0, max_rot_deg=16.0) == pytest.approx(3 / 4)
    assert success_rate(e_t, e_r, 8.0, max_rot_deg=16.0) == pytest.approx(2 / 4)
    # rotation-only (ReFeree): correct retrieval and e_r < 10 deg
    assert rotation_success_rate([True, True, False, True], e_r) == pytest.approx(1 / 4)
    assert rotation_success_rate([False, True, True, True], e_r, max_rot_deg=16.0) == pytest.approx(2 / 4)


def test_localization_errors_refuse_headings_in_degrees():
    # a drive round a quarter circle whose headings follow the direction of travel in degrees
    a = np.linspace(0.0, np.pi / 2, 40)
    gt_rad = np.c_[50 * np.sin(a), 50 * (1 - np.cos(a)), a]
    gt_deg = gt_rad.copy()
    gt_deg[:, 2] = np.degrees(a)
    with pytest.raises(ValueError, match="degrees"):
        localization_errors(gt_rad, gt_deg)
    with pytest.raises(ValueError, match="degrees"):
        localization_errors(gt_deg, gt_rad)
    e_t, e_r = localization_errors(gt_rad, gt_rad)
    assert np.all(e_t == 0) and np.all(e_r == 0)


def test_summarize_hand_computed():
    gt = np.array([[0, 0, 0], [100, 0, 0], [200, 0, 0], [300, 0, 0]], float)
    db = np.array([[0, 0], [100, 0], [200, 0]], float)  # query 3 has no revisit
    retrieved = np.array([[0, 5], [200, 0], [200, 0], [200, 0]], float)  # correct, wrong, correct, wrong
    dist = np.array([0.1, 0.4, 0.2, 0.3])
    est = np.array([[1, 0, np.radians(2)], [150, 0, 0], [203, 4, np.radians(-4)], [np.nan] * 3])
    m = summarize(gt, retrieved, dist, db, radius_m=20.0, T_map_query_est=est)
    assert m.n_queries == 4
    assert m.recall_at_1 == pytest.approx(0.5)
    # sorted: q0 (T, rev) q2 (T, rev) q3 (F, no rev) q1 (F, rev)
    # delta=0.2: TP=2 FP=0 FN=1 -> P=1 R=2/3 F1=0.8 ; delta=0.3: TP=2 FP=1 FN=1 -> F1=2/3 ; 0.4: P=1/2 R=1 F1=2/3
    assert m.f1_max == pytest.approx(0.8)
    # successes: q0 (1 m, 2 deg) and q2 (5 m, 4 deg); q1 is 50 m off
    assert m.sr == pytest.approx(0.5)
    assert m.e_t_m == pytest.approx(3.0) and m.e_r_deg == pytest.approx(3.0)
    only_rot = summarize(gt, retrieved, dist, db, 20.0, est, rotation_only=True)
    assert only_rot.sr == pytest.approx(0.5) and np.isnan(only_rot.e_t_m)
    no_pose = summarize(gt, retrieved, dist, db, 20.0)
    assert np.isnan(no_pose.sr) and np.isnan(no_pose.e_r_deg)
    none_ok = summarize(gt, retrieved, dist, db, 20.0, np.full((4, 3), np.nan))
    assert none_ok.sr == 0.0 and np.isnan(none_ok.e_t_m) and np.isnan(none_ok.e_r_deg)
    assert set(m.as_dict()) == {"recall_at_1", "f1_max", "sr", "e_r_deg", "e_t_m", "n_queries"}


def test_radii():
    assert RADIUS_M == {"oord": 25.0, "mulran": 20.0, "boreas": 20.0}
    assert radius_for("OORD") == 25.0 and radius_for("boreas-2021") == 20.0 and radius_for("oxford") == 25.0
    with pytest.raises(ConfigError, match="no evaluation radius"):
        radius_for("kitti")


def test_revisit_breakdown_hand_computed():
    from reradar_core.evaluation import revisit_breakdown

    # query:     0     1      2      3      4      5
    # revisit:   T     T      T      T      F      F
    # correct:   T     T      F      F      F      F
    # answered:  T     T      F      T      T      F     (F = rejected, e.g. not_localized)
    # success:   T     F      F      F      T      F     (4: a good pose although no keyframe lies within R)
    revisit = np.array([1, 1, 1, 1, 0, 0], bool)
    correct = np.array([1, 1, 0, 0, 0, 0], bool)
    answered = np.array([1, 1, 0, 1, 1, 0], bool)
    success = np.array([1, 0, 0, 0, 1, 0], bool)
    b = revisit_breakdown(correct, revisit, success, answered)
    assert (b.n_queries, b.n_revisit, b.n_no_match) == (6, 4, 2)
    assert b.recall_at_1_revisit == pytest.approx(2 / 4) and b.recall_at_1_all == pytest.approx(2 / 6)
    assert b.sr_revisit == pytest.approx(1 / 4) and b.sr_all == pytest.approx(2 / 6)
    assert b.has_rejection
    assert (b.n_rejected_no_match, b.n_wrong_pose_no_match, b.n_correct_pose_no_match) == (1, 0, 1)
    assert b.correct_rejection_rate == pytest.approx(0.5) and b.wrong_pose_rate_no_match == 0.0
    assert (b.n_rejected_revisit, b.n_wrong_pose_revisit) == (1, 2)  # 2 rejected; 1 and 3 answered wrongly

    # a method that always answers has no rejection figures; without a success rule no SR either
    nr = revisit_breakdown(correct, revisit, success)
    assert not nr.has_rejection and nr.n_rejected_no_match is None and np.isnan(nr.correct_rejection_rate)
    assert nr.sr_revisit == pytest.approx(1 / 4)
    plain = revisit_breakdown(correct, revisit)
    assert np.isnan(plain.sr_revisit) and np.isnan(plain.sr_all) and plain.recall_at_1_revisit == 0.5
    # no revisit query at all: the headline is undefined (NaN), never a misleading 0
    none = revisit_breakdown(np.zeros(3, bool), np.zeros(3, bool), np.zeros(3, bool), np.zeros(3, bool))
    assert np.isnan(none.recall_at_1_revisit) and none.correct_rejection_rate == 1.0
    with pytest.raises(ValueError, match="differ in length"):
        revisit_breakdown(correct, revisit[:3])
    with pytest.raises(ValueError, match="answered needs success"):
        revisit_breakdown(correct, revisit, None, answered)


def test_proportion_interval_wilson_known_answers():
    from reradar_core.evaluation import proportion_interval

    # Wilson score interval, z = 1.959964: 8 of 10 -> 0.4902 .. 0.9433; 0 of 20 -> 0 .. 0.1611; 20 of 20 -> 0.8389 .. 1
    lo, hi = proportion_interval(8, 10)
    assert abs(lo - 0.4902) < 5e-4 and abs(hi - 0.9433) < 5e-4
    lo, hi = proportion_interval(0, 20)
    assert lo == 0.0 and abs(hi - 0.1611) < 5e-4
    lo, hi = proportion_interval(20, 20)
    assert abs(lo - 0.8389) < 5e-4 and hi == 1.0
    assert all(np.isnan(proportion_interval(0, 0)))


def test_metrics_refuse_transposed_positions_and_mismatched_error_arrays():
    """QA session 38: (2, Q) positions passed a ">= 2 columns" test and broadcast errors counted other queries."""
    q = np.array([[0.0, 0.0], [50.0, 0.0], [100.0, 0.0], [150.0, 0.0]])
    with pytest.raises(ValueError, match=r"\(Q, 2\)"):
        has_revisit(q, q.T, 20.0)
    e_t, e_r = np.array([1.0, 30.0, 1.0, 1.0]), np.array([1.0, 1.0, 20.0, 1.0])
    assert success_rate(e_t, e_r, 20.0) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="one shape"):
        success_rate(e_t, e_r[:, None], 20.0)
    with pytest.raises(ValueError, match="one shape"):
        rotation_success_rate([True, True], e_r)
