"""Metric adapter, rotation stress helpers and the feature cache, with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.benchmark.cache import FeatureCache
from reradar_core.benchmark.metrics import make_outcome, summarise
from reradar_core.benchmark.rotation import heading_offsets, rotate_pose, rotate_scan
from reradar_core.benchmark.synthetic import render_scan, synthetic_world
from reradar_core.geometry.se2 import compose
from reradar_core.landmarks import detect_landmarks

DB = np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [100.0, 0.0, 0.0], [150.0, 0.0, 0.0]])
QUERY = np.array([[1.0, 0.0, 0.1], [52.0, 0.0, 0.0], [99.0, 0.0, 0.0], [148.0, 0.0, -0.05]])


def test_summary_known_answer_for_pose_methods():
    retrieved = np.array([0, 1, 3, 3])  # third query wrong (50 m away)
    est = np.array([[1.5, 0.0, 0.1 + np.deg2rad(2.0)], [52.0, 3.0, 0.0], [np.nan] * 3,
                    [148.0, 0.0, -0.05 + np.deg2rad(20.0)]])  # last: rotation 20 deg -> failure
    out = make_outcome(retrieved, np.array([0.1, 0.2, 0.9, 0.3]), est, QUERY, DB, 20.0, "pose")
    s = summarise(out, QUERY, DB, 20.0, "pose")
    assert s["recall@1"] == pytest.approx(75.0)
    assert s["sr"] == pytest.approx(50.0)
    assert s["e_t_m"] == pytest.approx((0.5 + 3.0) / 2)
    assert s["e_r_deg"] == pytest.approx(1.0)
    # threshold at 0.3 accepts three queries, all correct; the wrong one (0.9) is rejected -> P=1, R=3/4
    assert s["f1max"] == pytest.approx(100 * 2 * 0.75 / 1.75)
    assert s["wrong_pose_pct"] == pytest.approx(25.0)  # the last query was answered with a 20-deg-off pose
    # 95 % Wilson intervals over the 4 revisit queries: 3 of 4 correct, 2 of 4 successes
    assert s["recall@1_ci95"] == pytest.approx([30.06, 95.44], abs=0.01)
    assert s["sr_ci95"] == pytest.approx([15.00, 85.00], abs=0.01)


def test_summary_heading_rule_and_not_applicable():
    retrieved = np.array([0, 1, 3, 3])
    est = np.array([compose(DB[j], [0.0, 0.0, QUERY[i, 2] - DB[j, 2] + np.deg2rad(e)])
                    for i, (j, e) in enumerate(zip(retrieved, [3.0, 1.0, 0.0, 12.0], strict=True))])
    out = make_outcome(retrieved, np.zeros(4), est, QUERY, DB, 20.0, "heading")
    s = summarise(out, QUERY, DB, 20.0, "heading")
    assert s["sr"] == pytest.approx(50.0)  # queries 0, 1 (query 2 wrong place, query 3 rotation 12 deg)
    assert s["e_r_deg"] == pytest.approx(2.0)
    assert s["e_t_m"] is None and s["wrong_pose_pct"] is None
    s2 = summarise(make_outcome(retrieved, np.zeros(4), np.full((4, 3), np.nan), QUERY, DB, 20.0, "none"),
                   QUERY, DB, 20.0, "none")
    assert s2["sr"] is None and s2["e_r_deg"] is None and s2["recall@1"] == pytest.approx(75.0)
    assert s2["sr_ci95"] is None and s2["recall@1_ci95"] is not None


def test_rotated_scan_sees_landmarks_turned_by_the_heading_offset():
    """A sensor turned by +yaw sees a point p at R(-yaw) p; the rotated ground truth is compose(T, yaw)."""
    world = synthetic_world(seed=2)
    pose = np.array([10.0, -5.0, 0.7])
    yaw = heading_offsets(1, seed=4, num_azimuths=400)[0]
    assert np.isclose(np.mod(yaw / (2 * np.pi / 400), 1.0), 0.0, atol=1e-9)
    turned = rotate_scan(render_scan(world, pose, noise_seed=0), yaw)
    direct = render_scan(world, rotate_pose(pose, yaw), noise_seed=0)
    a = detect_landmarks(turned)
    b = detect_landmarks(direct)
    # same landmarks up to the sensor's noise (rotate_scan rolls the noise too): compare point sets
    d = np.linalg.norm(a.xy_m[:, None] - b.xy_m[None], axis=-1).min(axis=1)
    assert np.median(d) < 0.5
    assert np.allclose(rotate_pose(pose, yaw), compose(pose, [0, 0, yaw]))


def test_feature_cache_round_trip_and_staleness(tmp_path):
    src = tmp_path / "scan.png"
    src.write_bytes(b"abc")
    with FeatureCache("m-1", "seq", root=tmp_path / "c") as c:
        assert c.get("scan", src) is None
        c.put("scan", {"a": np.arange(3.0), "b": np.ones((2, 2), np.float16)}, 12.5, src)
    with FeatureCache("m-1", "seq", root=tmp_path / "c") as c:
        rec, ms = c.get("scan", src)
        assert ms == 12.5 and rec["b"].dtype == np.float16 and np.allclose(rec["a"], [0, 1, 2])
        src.write_bytes(b"abcd")  # the scan changed -> recompute
        assert c.get("scan", src) is None


def test_feature_cache_in_use_by_another_run_is_left_alone(tmp_path):
    """HDF5 locks a file open for writing against other processes: that file must not be touched."""
    import subprocess
    import sys

    src = tmp_path / "scan.png"
    src.write_bytes(b"abc")
    with FeatureCache("m-1", "seq", root=tmp_path / "c") as first:
        first.put("scan", {"a": np.ones(2)}, 1.0, src)
        path = first.path
    holder = subprocess.Popen([sys.executable, "-c", "import h5py, sys, time; f = h5py.File(sys.argv[1], 'a'); "
                               "print('held', flush=True); time.sleep(60)", str(path)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        other = FeatureCache("m-1", "seq", root=tmp_path / "c")
        assert not other.enabled and other.get("scan", src) is None
        other.put("scan", {"a": np.zeros(2)}, 2.0, src)  # no-op
        other.close()
    finally:
        holder.kill()
        holder.wait()
    with FeatureCache("m-1", "seq", root=tmp_path / "c") as c:
        rec, ms = c.get("scan", src)
        assert ms == 1.0 and np.allclose(rec["a"], 1.0)  # the other run's file survived intact


def test_summary_splits_revisit_and_no_match_queries():
    """Single-session shape: half the queries have no keyframe within R; the headline divides by revisits."""
    db = np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0]])
    query = np.array([[1.0, 0.0, 0.0], [52.0, 0.0, 0.0], [200.0, 0.0, 0.0], [300.0, 0.0, 0.0]])
    retrieved = np.array([0, 1, 1, 0])
    est = np.array([[1.2, 0.1, 0.01], [np.nan] * 3,  # q1: not_localized although it has a match
                    [49.0, 0.0, 0.0],  # q2: no match, localized at a wrong pose (150 m off)
                    [np.nan] * 3])  # q3: no match, correctly rejected
    out = make_outcome(retrieved, np.array([0.1, 0.2, 0.3, 0.4]), est, query, db, 20.0, "pose")
    s = summarise(out, query, db, 20.0, "pose")
    assert (s["n_queries"], s["n_revisit"], s["n_no_match"]) == (4, 2, 2)
    assert s["recall@1"] == pytest.approx(100.0) and s["recall@1_all"] == pytest.approx(50.0)
    assert s["sr"] == pytest.approx(50.0) and s["sr_all"] == pytest.approx(25.0)
    assert s["rejection"] == "not_localized"
    assert s["correct_rejection_pct"] == pytest.approx(50.0) and s["wrong_pose_no_match_pct"] == pytest.approx(50.0)
    assert (s["n_rejected_no_match"], s["n_wrong_pose_no_match"], s["n_correct_pose_no_match"]) == (1, 1, 0)
    assert (s["n_rejected_revisit"], s["n_wrong_pose_revisit"]) == (1, 0)
    assert s["wrong_pose_pct"] == pytest.approx(25.0)
    # the same answers from a method without rejection (heading only): rejection figures not applicable
    h = summarise(make_outcome(retrieved, np.zeros(4), np.nan_to_num(est), query, db, 20.0, "heading"),
                  query, db, 20.0, "heading")
    assert h["rejection"] is None and h["correct_rejection_pct"] is None and h["n_rejected_no_match"] is None
    assert h["recall@1"] == pytest.approx(100.0) and h["recall@1_all"] == pytest.approx(50.0)


def test_covariance_calibration_of_errors_drawn_from_the_covariances():
    # 4,000 answers whose errors are drawn from their own (varied, correlated) covariances: 95 % lie inside the 95 %
    # ellipsoid and the mean normalised squared error is 3; the same errors against covariances 4x too small are not
    from reradar_core.benchmark.metrics import covariance_calibration

    rng = np.random.default_rng(0)
    q = 4000
    a = rng.normal(size=(q, 3, 3)) * np.array([0.1, 0.1, 0.003])[None, :, None]
    cov = a @ a.transpose(0, 2, 1) + np.diag([1e-3, 1e-3, 1e-6])
    err = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.normal(size=(q, 3)))
    gt = np.column_stack([rng.uniform(0, 100, q), rng.uniform(0, 100, q), rng.uniform(-3, 3, q)])
    est = gt - err
    out = make_outcome(np.zeros(q, np.int64), np.zeros(q), est, gt, gt[:1], 1e9, "pose")
    assert covariance_calibration(out, gt, 1e9) is None  # no covariances in the outcome
    out.pose_covariance = cov
    cal = covariance_calibration(out, gt, 1e9)
    assert cal["n"] == q
    assert cal["nees"] == pytest.approx(3.0, abs=0.15)
    assert cal["inside_95_pct"] == pytest.approx(95.0, abs=1.0)
    assert cal["inside_50_pct"] == pytest.approx(50.0, abs=2.5)
    assert cal["position_inside_95_pct"] == pytest.approx(95.0, abs=1.0)
    assert cal["heading_inside_95_pct"] == pytest.approx(95.0, abs=1.0)
    assert cal["rms_position_m"] == pytest.approx(cal["predicted_rms_position_m"], rel=0.05)
    out.pose_covariance = cov / 16.0
    tight = covariance_calibration(out, gt, 1e9)
    assert tight["nees"] == pytest.approx(48.0, rel=0.06) and tight["inside_95_pct"] < 40.0
    # only successful answers with a covariance count; none: None
    out.pose_covariance = cov.copy()
    out.pose_covariance[: q // 2] = np.nan
    assert covariance_calibration(out, gt, 1e9)["n"] == q // 2
    out.pose_covariance = np.full_like(cov, np.nan)
    assert covariance_calibration(out, gt, 1e9) is None
