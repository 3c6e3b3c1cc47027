"""Adapter from per-query benchmark outcomes to the paper's metrics (``reradar_core.evaluation``).

Conventions (``reradar_core.evaluation.metrics``): a top-1 retrieval is correct within R of the query's
ground-truth position (25 m OORD, 20 m MulRan / Boreas); Recall@1 and SR divide by all queries; F1max by
the RaPlace protocol; ê_r, ê_t are means over successful queries. The results report percentages.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from reradar_core.evaluation import (
    has_revisit,
    localization_errors,
    localization_success,
    precision_recall_curve,
    retrieval_correct,
    summarize,
)

__all__ = ["QueryOutcome", "make_outcome", "summarise", "pr_curve"]


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
    """

    retrieved: np.ndarray
    distance: np.ndarray
    est_pose: np.ndarray
    correct: np.ndarray
    positive: np.ndarray
    heading_err_deg: np.ndarray
    trans_err_m: np.ndarray


def make_outcome(retrieved: np.ndarray, distance: np.ndarray, est_pose: np.ndarray, query_poses: np.ndarray,
                 db_poses: np.ndarray, radius_m: float, sr_rule: str) -> QueryOutcome:
    """Build the outcome arrays (correctness, revisits, errors) from the raw answers."""
    correct = retrieval_correct(query_poses, db_poses[retrieved, :2], radius_m)
    positive = has_revisit(query_poses, db_poses[:, :2], radius_m)
    e_t, e_r = localization_errors(est_pose, query_poses)
    if sr_rule != "pose":
        e_t = np.full_like(e_t, np.nan)
    return QueryOutcome(np.asarray(retrieved, np.int64), np.asarray(distance, np.float64), est_pose, correct,
                        positive, e_r, e_t)


def summarise(out: QueryOutcome, query_poses: np.ndarray, db_poses: np.ndarray, radius_m: float,
              sr_rule: str) -> dict[str, Any]:
    """Recall@1, F1max, SR (percent), ê_r (deg), ê_t (m), n_queries; None where not applicable.

    ``sr_rule``: ``pose`` (translation < R and rotation < 10 deg), ``heading`` (correct retrieval and
    rotation < 10 deg, the paper's rule for ReFeree) or ``none`` (SR, ê_r, ê_t not applicable).
    ``wrong_pose_pct`` (``pose`` rule only): queries answered with a pose that misses the SR rule, percent.
    """
    m = summarize(query_poses, db_poses[out.retrieved, :2], out.distance, db_poses[:, :2], radius_m,
                  T_map_query_est=None if sr_rule == "none" else out.est_pose,
                  rotation_only=sr_rule == "heading")

    def pct(v: float) -> float | None:
        return None if not np.isfinite(v) else 100.0 * float(v)

    def val(v: float) -> float | None:
        return None if not np.isfinite(v) else float(v)

    wrong = None
    if sr_rule == "pose" and len(out.retrieved):
        # answered with a pose (the method said "localized") that misses the SR rule: what a user must not get
        answered = np.isfinite(out.est_pose[:, 0])
        good = localization_success(out.trans_err_m, out.heading_err_deg, radius_m)
        wrong = 100.0 * float(np.mean(answered & ~good))
    return {"recall@1": pct(m.recall_at_1), "f1max": pct(m.f1_max), "sr": pct(m.sr),
            "e_r_deg": val(m.e_r_deg), "e_t_m": val(m.e_t_m), "n_queries": int(m.n_queries),
            "n_with_revisit": int(np.count_nonzero(out.positive)), "wrong_pose_pct": wrong}


def pr_curve(distance: np.ndarray, correct: np.ndarray, positive: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(precision, recall) over thresholds, RaPlace protocol (``evaluation.precision_recall_curve``)."""
    pr = precision_recall_curve(distance, correct, positive)
    return pr.precision, pr.recall
