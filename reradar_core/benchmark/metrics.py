"""Adapter from per-query benchmark outcomes to the paper's metrics (``reradar_core.evaluation``).

Conventions (``reradar_core.evaluation.metrics``): a top-1 retrieval is correct within R of the query's
ground-truth position (25 m OORD, 20 m MulRan / Boreas). The headline ``recall@1`` and ``sr`` divide by the
*revisit* queries (those with a database keyframe within R); ``recall@1_all`` and ``sr_all`` divide by all
queries (the paper's GT). Queries without a match are scored by rejection: ``correct_rejection_pct`` and
``wrong_pose_no_match_pct``. "Rejected" means, per kind of method:

- full-pose methods (ReRadar): the answer has no pose, i.e. the service's status ``not_localized``;
- retrieval-only and heading-only methods (RingKey, RaPlace, RadVLAD, ResNet18-NetVLAD, ReFeree): no
  rejection; they answer every query (a distance threshold would have to be chosen without the query
  sequence, and none is), so the rejection figures are ``None`` (not applicable).

F1max by the RaPlace protocol (unchanged); ê_r, ê_t are means over all successful queries. Percentages.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from reradar_core.evaluation import (
    has_revisit,
    localization_errors,
    localization_success,
    pose_error,
    precision_recall_curve,
    proportion_interval,
    retrieval_correct,
    revisit_breakdown,
    rotation_success,
    summarize,
)

#: What "rejected" means for each success rule (results.json ``rejection``; None = the method never rejects).
REJECTION_RULES: dict[str, str | None] = {"pose": "not_localized", "heading": None, "none": None}

__all__ = ["QueryOutcome", "covariance_calibration", "covariance_report", "make_outcome", "summarise", "pr_curve"]

#: ellipsoid probabilities the benchmark reports the pose covariance's coverage at
COVERAGE_LEVELS = (0.5, 0.9, 0.95, 0.99)


@dataclass
class QueryOutcome:
    """Per-query results of one method on one query sequence (arrays of length Q).

    Attributes:
        retrieved: (Q,) int64 database index of the answer.
        distance: (Q,) float64 descriptor distance of the answer (lower = more confident).
        est_pose: (Q, 3) estimated T_map_query (NaN rows: no estimate). For heading-only methods the
            translation is the retrieved keyframe's and only the yaw is an estimate.
        correct: (Q,) bool, answer within R of the query's true position.
        positive: (Q,) bool, the database holds a keyframe within R (a true revisit).
        heading_err_deg: (Q,) |yaw error| degrees (NaN without estimate).
        trans_err_m: (Q,) translation error, metres (NaN without a pose estimate).
        pose_covariance: (Q, 3, 3) covariance of ``est_pose`` (x m, y m, yaw rad; NaN rows: none), or None when
            the method gives none (every method but ReRadar).
    """

    retrieved: np.ndarray
    distance: np.ndarray
    est_pose: np.ndarray
    correct: np.ndarray
    positive: np.ndarray
    heading_err_deg: np.ndarray
    trans_err_m: np.ndarray
    pose_covariance: np.ndarray | None = None


def make_outcome(retrieved: np.ndarray, distance: np.ndarray, est_pose: np.ndarray, query_poses: np.ndarray,
                 db_poses: np.ndarray, radius_m: float, sr_rule: str,
                 query_pose_gt: np.ndarray | None = None) -> QueryOutcome:
    """Build the outcome arrays (correctness, revisits, errors) from the raw answers.

    ``query_pose_gt``: (Q, 3) ground truth of the estimated poses when it refers to another time than
    ``query_poses`` (mid-sweep, docs/CONVENTIONS.md); retrieval correctness always uses ``query_poses``.
    """
    correct = retrieval_correct(query_poses, db_poses[retrieved, :2], radius_m)
    positive = has_revisit(query_poses, db_poses[:, :2], radius_m)
    e_t, e_r = localization_errors(est_pose, query_poses if query_pose_gt is None else query_pose_gt)
    if sr_rule != "pose":
        e_t = np.full_like(e_t, np.nan)
    return QueryOutcome(np.asarray(retrieved, np.int64), np.asarray(distance, np.float64), est_pose, correct,
                        positive, e_r, e_t)


def summarise(out: QueryOutcome, query_poses: np.ndarray, db_poses: np.ndarray, radius_m: float,
              sr_rule: str, query_pose_gt: np.ndarray | None = None) -> dict[str, Any]:
    """The per-sequence metrics of one method (percentages; None where not applicable).

    ``sr_rule``: ``pose`` (translation < R and rotation < 10 deg; a query without a pose is rejected),
    ``heading`` (correct retrieval and rotation < 10 deg, the paper's rule for ReFeree; never rejects) or
    ``none`` (SR, ê_r, ê_t not applicable; never rejects).

    Keys: ``recall@1`` / ``sr`` (over revisit queries, the headline) with their 95 % Wilson intervals
    ``recall@1_ci95`` / ``sr_ci95`` ([low, high] percent, over the same revisit queries: how far the figure may lie
    from what many more such queries would give), ``recall@1_all`` / ``sr_all`` (over all queries), ``f1max``
    (None without a revisit query: F1 is undefined when no answer can be a true positive),
    ``e_r_deg``, ``e_t_m``, counts ``n_queries`` / ``n_revisit`` / ``n_no_match``,
    ``rejection`` (what rejected means, None = never rejects), on no-match queries ``correct_rejection_pct``,
    ``wrong_pose_no_match_pct`` and their counts, on revisit queries ``n_rejected_revisit`` and
    ``n_wrong_pose_revisit``, and ``wrong_pose_pct`` (answered with a pose that misses the SR rule, percent of
    all queries; ``pose`` rule only).
    """
    m = summarize(query_poses, db_poses[out.retrieved, :2], out.distance, db_poses[:, :2], radius_m,
                  T_map_query_est=None if sr_rule == "none" else out.est_pose,
                  rotation_only=sr_rule == "heading", T_map_query_gt=query_pose_gt)

    def pct(v: float) -> float | None:
        return None if not np.isfinite(v) else 100.0 * float(v)

    def val(v: float) -> float | None:
        return None if not np.isfinite(v) else float(v)

    success = answered = None
    if sr_rule == "pose":
        success = localization_success(out.trans_err_m, out.heading_err_deg, radius_m)
        answered = np.isfinite(out.est_pose[:, 0])  # no pose = not_localized = rejected
    elif sr_rule == "heading":
        success = rotation_success(out.correct, out.heading_err_deg)
    b = revisit_breakdown(out.correct, out.positive, success, answered)
    wrong = None
    if sr_rule == "pose" and len(out.retrieved):
        # answered with a pose (the method said "localized") that misses the SR rule: what a user must not get
        wrong = 100.0 * float(np.mean(answered & ~success))  # type: ignore[operator]
    def ci95(hits: np.ndarray | None) -> list[float] | None:
        if hits is None or b.n_revisit == 0:
            return None
        lo, hi = proportion_interval(int(np.count_nonzero(hits[out.positive])), b.n_revisit)
        return [100.0 * lo, 100.0 * hi]

    return {"recall@1": pct(b.recall_at_1_revisit), "recall@1_ci95": ci95(out.correct),
            "sr": pct(b.sr_revisit), "sr_ci95": ci95(success),
            "recall@1_all": pct(m.recall_at_1), "sr_all": pct(m.sr),
            # no revisit query: no answer can be a true positive, recall and F1 are 0/0 (not 0)
            "f1max": pct(m.f1_max) if b.n_revisit else None,
            "e_r_deg": val(m.e_r_deg), "e_t_m": val(m.e_t_m), "n_queries": int(m.n_queries),
            "n_revisit": b.n_revisit, "n_no_match": b.n_no_match, "rejection": REJECTION_RULES[sr_rule],
            "correct_rejection_pct": pct(b.correct_rejection_rate),
            "wrong_pose_no_match_pct": pct(b.wrong_pose_rate_no_match),
            "n_rejected_no_match": b.n_rejected_no_match, "n_wrong_pose_no_match": b.n_wrong_pose_no_match,
            "n_correct_pose_no_match": b.n_correct_pose_no_match, "n_rejected_revisit": b.n_rejected_revisit,
            "n_wrong_pose_revisit": b.n_wrong_pose_revisit, "wrong_pose_pct": wrong}


def pr_curve(distance: np.ndarray, correct: np.ndarray, positive: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(precision, recall) over thresholds, RaPlace protocol (``evaluation.precision_recall_curve``)."""
    pr = precision_recall_curve(distance, correct, positive)
    return pr.precision, pr.recall


def covariance_calibration(out: QueryOutcome, pose_gt: np.ndarray, radius_m: float) -> dict[str, Any] | None:
    """How well the answers' pose covariances (``out.pose_covariance``) describe their errors (``covariance_report``),
    over the successful answers that have one.

    Args:
        out: the outcome (its ``est_pose``, ``trans_err_m``, ``heading_err_deg`` and ``pose_covariance``: (Q, 3, 3) of
            each ``est_pose``, x m, y m, yaw rad, NaN where none).
        pose_gt: (Q, 3) ground truth of the estimated poses (x m, y m, yaw rad; mid-sweep).
        radius_m: the success radius (metres; with 10 deg).
    Returns:
        ``covariance_report``'s figures, or None when no successful answer has a covariance.
    """
    if out.pose_covariance is None:
        return None
    cov = np.asarray(out.pose_covariance, np.float64).reshape(-1, 3, 3)
    success = localization_success(out.trans_err_m, out.heading_err_deg, radius_m)
    m = success & np.isfinite(cov).all(axis=(1, 2))
    if not m.any():
        return None
    return covariance_report(pose_error(np.asarray(pose_gt)[m], np.asarray(out.est_pose)[m]), cov[m])


def covariance_report(errors: np.ndarray, covariance: np.ndarray) -> dict[str, Any]:
    """Calibration figures of pose covariances against the poses' errors.

    Args:
        errors: (n, 3) ground truth - estimate (x m, y m, yaw rad; the heading wrapped), n >= 1.
        covariance: (n, 3, 3) each estimate's covariance (x m, y m, yaw rad).
    Returns:
        ``n``, ``nees`` (mean normalised squared error e^T C^-1 e: 3 when calibrated), ``inside_P_pct`` (percent of
        errors inside the covariance's P ellipsoid, 3-DoF, P in ``COVERAGE_LEVELS``; P when calibrated),
        ``position_inside_95_pct`` / ``heading_inside_95_pct`` (the same for position and heading alone), and the
        RMS errors against the RMS the covariances predict (``rms_position_m`` / ``predicted_rms_position_m``,
        ``rms_heading_deg`` / ``predicted_rms_heading_deg``).
    """
    from scipy.stats import chi2

    e = np.asarray(errors, np.float64).reshape(-1, 3)
    c = np.asarray(covariance, np.float64).reshape(-1, 3, 3)
    d2 = np.einsum("ni,ni->n", e, np.linalg.solve(c, e[..., None])[..., 0])
    d2_pos = np.einsum("ni,ni->n", e[:, :2], np.linalg.solve(c[:, :2, :2], e[:, :2, None])[..., 0])
    d2_yaw = e[:, 2] ** 2 / c[:, 2, 2]
    res: dict[str, Any] = {"n": int(len(e)), "nees": float(d2.mean())}
    for p in COVERAGE_LEVELS:
        res[f"inside_{round(p * 100)}_pct"] = 100.0 * float(np.mean(d2 <= chi2.ppf(p, 3)))
    res["position_inside_95_pct"] = 100.0 * float(np.mean(d2_pos <= chi2.ppf(0.95, 2)))
    res["heading_inside_95_pct"] = 100.0 * float(np.mean(d2_yaw <= chi2.ppf(0.95, 1)))
    res["rms_position_m"] = float(np.sqrt((e[:, :2] ** 2).sum(1).mean()))
    res["predicted_rms_position_m"] = float(np.sqrt((c[:, 0, 0] + c[:, 1, 1]).mean()))
    res["rms_heading_deg"] = float(np.degrees(np.sqrt((e[:, 2] ** 2).mean())))
    res["predicted_rms_heading_deg"] = float(np.degrees(np.sqrt(c[:, 2, 2].mean())))
    return res
