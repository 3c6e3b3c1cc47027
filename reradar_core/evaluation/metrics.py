"""Place recognition and localization metrics (paper, Sec. Evaluation Metrics).

- Recall@1 = TP / GT: a query is a true positive when its top-1 retrieval lies within R of the query's
  ground-truth position; GT counts *all* queries (also those with no database entry within R).
- F1max = max over a descriptor-distance threshold delta of 2 P R / (P + R), RaPlace protocol.
- Localization: translation error e_t [m] and rotation error e_r [deg] of the estimated map-frame pose;
  success when e_t < R and e_r < 10 deg jointly (BEVPlace++), SR = N_succ / GT; mean e_t and e_r are taken
  over successful queries only. Methods without translation (ReFeree) succeed on a correct retrieval with
  e_r < 10 deg.

Radii R: 25 m on OORD, 20 m on MulRan and Boreas (``RADIUS_M``). Rates are fractions in [0, 1] (the paper
prints percentages).

Revisit-aware figures (``revisit_breakdown``): the paper divides by all queries, which caps Recall@1 and SR
at the share of queries that *have* a database entry within R (on a single-session split that can be half).
The breakdown separates the two kinds of query: *revisit* queries (a database entry within R) give Recall@1
and SR over revisits (the benchmark's headline); *no-match* queries can only be answered correctly by a
rejection, so they give the correct-rejection rate and the wrong-pose rate. What "rejected" means depends on
the method and is the caller's ``answered`` mask (ReRadar: status ``not_localized``); methods that always
answer have no rejection and those two rates are not applicable.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reradar_core.errors import ConfigError
from reradar_core.geometry.se2 import check_yaw_radians, wrap_angle

__all__ = [
    "RADIUS_M",
    "MAX_ROTATION_ERROR_DEG",
    "LocalizationMetrics",
    "PrecisionRecall",
    "radius_for",
    "retrieval_correct",
    "has_revisit",
    "recall_at_1",
    "precision_recall_curve",
    "f1_max",
    "localization_errors",
    "pose_error",
    "localization_success",
    "success_rate",
    "rotation_success",
    "rotation_success_rate",
    "summarize",
    "RevisitBreakdown",
    "revisit_breakdown",
]

#: Place recognition / localization radius per dataset family, metres (paper, Sec. Evaluation Metrics).
RADIUS_M: dict[str, float] = {"oord": 25.0, "mulran": 20.0, "boreas": 20.0}
#: Rotation error bound of a successful localization, degrees (paper, following BEVPlace++).
MAX_ROTATION_ERROR_DEG = 10.0


def radius_for(dataset: str) -> float:
    """The paper's radius for a dataset family or preset name (``oord``, ``mulran``, ``boreas*``, ``oxford``).

    Oxford Radar RobotCar shares OORD's sensor and is evaluated with OORD's 25 m here.
    """
    key = dataset.lower()
    if key.startswith("boreas"):
        return RADIUS_M["boreas"]
    if key == "oxford":
        return RADIUS_M["oord"]
    if key not in RADIUS_M:
        raise ConfigError(f"no evaluation radius for dataset {dataset!r}; known: {sorted(RADIUS_M)}")
    return RADIUS_M[key]


def _xy(name: str, a: np.ndarray) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] not in (2, 3):  # (2, Q) transposed would pass a ">= 2" test with Q >= 2
        raise ValueError(f"{name} must be (Q, 2) positions in metres (or (Q, 3) poses), got shape {arr.shape}")
    return arr[:, :2]


def retrieval_correct(query_xy: np.ndarray, retrieved_xy: np.ndarray, radius_m: float) -> np.ndarray:
    """(Q,) bool: top-1 retrieval within ``radius_m`` of the query's ground truth.

    Args:
        query_xy: (Q, 2) ground-truth query positions, metres, map frame ((Q, 3) poses accepted).
        retrieved_xy: (Q, 2) positions of each query's top-1 database entry; NaN rows (nothing retrieved)
            count as wrong.
        radius_m: the radius R, metres.
    """
    q = _xy("query_xy", query_xy)
    r = _xy("retrieved_xy", retrieved_xy)
    if q.shape != r.shape:
        raise ValueError(f"query_xy {q.shape} and retrieved_xy {r.shape} differ in length")
    d = np.linalg.norm(q - r, axis=1)
    return np.where(np.isfinite(d), d <= radius_m, False)


def has_revisit(query_xy: np.ndarray, database_xy: np.ndarray, radius_m: float) -> np.ndarray:
    """(Q,) bool: some database entry lies within ``radius_m`` of each query's ground truth (a true revisit)."""
    from scipy.spatial import cKDTree

    q = _xy("query_xy", query_xy)
    db = _xy("database_xy", database_xy)
    if len(db) == 0 or len(q) == 0:
        return np.zeros(len(q), dtype=bool)
    dist, _ = cKDTree(db).query(q, k=1)
    return dist <= radius_m


def recall_at_1(query_xy: np.ndarray, retrieved_xy: np.ndarray, radius_m: float) -> float:
    """Recall@1 = TP / GT in [0, 1]; the denominator is all Q queries (0.0 for Q = 0)."""
    ok = retrieval_correct(query_xy, retrieved_xy, radius_m)
    return float(ok.mean()) if ok.size else 0.0


@dataclass
class PrecisionRecall:
    """Precision-recall sweep over the descriptor-distance threshold delta.

    Attributes:
        f1_max: max F1 over the thresholds (0 when no threshold gives a defined F1 > 0).
        precision: (T,) P(delta) = TP / (TP + FP).
        recall: (T,) R(delta) = TP / (TP + FN).
        thresholds: (T,) increasing delta values (the distinct finite top-1 distances); a query is accepted
            when its distance <= delta.
    """

    f1_max: float
    precision: np.ndarray
    recall: np.ndarray
    thresholds: np.ndarray

    def __iter__(self):  # unpack as (f1max, precision, recall, thresholds)
        return iter((self.f1_max, self.precision, self.recall, self.thresholds))


def precision_recall_curve(top1_distance: np.ndarray, is_correct: np.ndarray,
                           has_revisit: np.ndarray) -> PrecisionRecall:
    """Precision/recall/F1max by the RaPlace protocol; see ``f1_max``."""
    d = np.asarray(top1_distance, dtype=np.float64).reshape(-1)
    correct = np.asarray(is_correct, dtype=bool).reshape(-1)
    revisit = np.asarray(has_revisit, dtype=bool).reshape(-1)
    if not (d.shape == correct.shape == revisit.shape):
        raise ValueError(
            f"top1_distance {d.shape}, is_correct {correct.shape} and has_revisit {revisit.shape} differ"
        )
    if np.any(np.isnan(d)):
        raise ValueError("top1_distance contains NaN (use +inf for a query with no candidate)")
    finite = np.isfinite(d)
    order = np.argsort(d, kind="stable")
    ds = d[order]
    acc_tp = np.cumsum(correct[order])  # accepted and correct after accepting the k+1 closest
    acc_fp = np.cumsum(~correct[order])
    acc_rev = np.cumsum(revisit[order])
    # One threshold per distinct finite distance; accepting d <= delta takes whole tie groups.
    n_fin = int(finite.sum())
    if n_fin == 0:
        empty = np.zeros(0)
        return PrecisionRecall(0.0, empty, empty, empty)
    last_of_group = np.flatnonzero(np.r_[ds[1:n_fin] != ds[: n_fin - 1], True])
    tp = acc_tp[last_of_group].astype(np.float64)
    fp = acc_fp[last_of_group].astype(np.float64)
    fn = revisit.sum() - acc_rev[last_of_group].astype(np.float64)  # rejected with a true revisit
    with np.errstate(divide="ignore", invalid="ignore"):
        precision = np.where(tp + fp > 0, tp / (tp + fp), 0.0)
        recall = np.where(tp + fn > 0, tp / (tp + fn), 0.0)
        f1 = np.where(precision + recall > 0, 2 * precision * recall / (precision + recall), 0.0)
    return PrecisionRecall(float(f1.max()), precision, recall, ds[last_of_group])


def f1_max(top1_distance: np.ndarray, is_correct: np.ndarray,
           has_revisit: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """F1max over a threshold delta on the top-1 descriptor distance (RaPlace protocol).

    A query with distance > delta is rejected: a true negative if it has no true revisit, a false negative
    otherwise. An accepted query is a true positive if its top-1 is within R (``is_correct``), otherwise a
    false positive. P = TP / (TP + FP), R = TP / (TP + FN), F1 = 2 P R / (P + R) (0 where undefined).

    Args:
        top1_distance: (Q,) descriptor distance of each query's top-1 (smaller = more confident); +inf for a
            query with no candidate (never accepted).
        is_correct: (Q,) bool, top-1 within R of the ground truth (``retrieval_correct``).
        has_revisit: (Q,) bool, the database holds an entry within R of the query (``has_revisit``).

    Returns:
        (f1max, precision (T,), recall (T,), thresholds (T,)), thresholds increasing.
    """
    return tuple(precision_recall_curve(top1_distance, is_correct, has_revisit))  # type: ignore[return-value]


def pose_error(T_map_query_gt: np.ndarray, T_map_query_est: np.ndarray) -> np.ndarray:
    """Signed pose errors, ground truth - estimate: (..., 3) float64 (x m, y m, yaw rad; the frame of the poses; the
    heading difference wrapped to (-pi, pi]), for (..., 3) poses. What a pose covariance describes (``e^T C^-1 e``)."""
    gt, est = np.asarray(T_map_query_gt, np.float64), np.asarray(T_map_query_est, np.float64)
    if gt.ndim == 0 or gt.shape[-1] != 3 or est.shape != gt.shape:
        raise ValueError(f"poses must both be (..., 3) (x, y, yaw) of one shape, got {gt.shape} and {est.shape}")
    e = gt - est
    e[..., 2] = wrap_angle(e[..., 2])
    return e


def localization_errors(T_map_query_est: np.ndarray, T_map_query_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-query pose errors.

    Args:
        T_map_query_est: (Q, 3) estimated poses (x [m], y [m], yaw [rad]); NaN rows = no estimate.
        T_map_query_gt: (Q, 3) ground-truth poses.

    Raises:
        ValueError: shapes differ or are not (Q, 3); ``ConfigError`` when either set of headings reads as degrees
            (``geometry.se2.check_yaw_radians``: beyond 2 pi and following the direction of travel as degrees).

    Returns:
        e_t_m: (Q,) Euclidean translation error, metres (NaN without an estimate).
        e_r_deg: (Q,) absolute heading error on the circle, degrees in [0, 180] (NaN without an estimate).
    """
    est = np.asarray(T_map_query_est, dtype=np.float64)
    gt = np.asarray(T_map_query_gt, dtype=np.float64)
    if est.ndim != 2 or est.shape[1] != 3 or est.shape != gt.shape:
        raise ValueError(f"poses must both be (Q, 3) (x, y, yaw), got {est.shape} and {gt.shape}")
    # headings in degrees would give errors of up to 180 "degrees" that are really radians read wrong
    check_yaw_radians(gt, "ground-truth poses")
    check_yaw_radians(est, "estimated poses")
    e_t = np.linalg.norm(est[:, :2] - gt[:, :2], axis=1)
    e_r = np.degrees(np.abs(wrap_angle(est[:, 2] - gt[:, 2])))
    return e_t, e_r


def localization_success(e_t_m: np.ndarray | float, e_r_deg: np.ndarray | float, radius_m: float,
                         max_rot_deg: float = MAX_ROTATION_ERROR_DEG) -> np.ndarray:
    """(Q,) bool (0-d for scalar errors): e_t < radius_m and e_r < max_rot_deg jointly; NaN errors are
    failures. The one success rule of the benchmark, the demo and ``localize --follow``."""
    e_t = np.asarray(e_t_m, dtype=np.float64)
    e_r = np.asarray(e_r_deg, dtype=np.float64)
    if e_t.shape != e_r.shape:  # (Q,) against (Q, 1) or (1,) would broadcast into another count
        raise ValueError(f"e_t_m and e_r_deg must have one shape, got {e_t.shape} and {e_r.shape}")
    with np.errstate(invalid="ignore"):
        return (e_t < radius_m) & (e_r < max_rot_deg)


def success_rate(e_t_m: np.ndarray, e_r_deg: np.ndarray, radius_m: float,
                 max_rot_deg: float = MAX_ROTATION_ERROR_DEG) -> float:
    """SR = N_succ / GT in [0, 1] (all queries in the denominator; 0.0 for none)."""
    ok = localization_success(e_t_m, e_r_deg, radius_m, max_rot_deg)
    return float(ok.mean()) if ok.size else 0.0


def rotation_success(retrieval_ok: np.ndarray, e_r_deg: np.ndarray,
                     max_rot_deg: float = MAX_ROTATION_ERROR_DEG) -> np.ndarray:
    """(Q,) bool success for methods without translation (ReFeree): correct retrieval and e_r < max_rot_deg."""
    e_r = np.asarray(e_r_deg, dtype=np.float64)
    ok = np.asarray(retrieval_ok, dtype=bool)
    if ok.shape != e_r.shape:
        raise ValueError(f"retrieval_ok and e_r_deg must have one shape, got {ok.shape} and {e_r.shape}")
    with np.errstate(invalid="ignore"):
        return ok & (e_r < max_rot_deg)


def rotation_success_rate(retrieval_ok: np.ndarray, e_r_deg: np.ndarray,
                          max_rot_deg: float = MAX_ROTATION_ERROR_DEG) -> float:
    """Rotation-only SR in [0, 1] (see ``rotation_success``)."""
    ok = rotation_success(retrieval_ok, e_r_deg, max_rot_deg)
    return float(ok.mean()) if ok.size else 0.0


@dataclass
class LocalizationMetrics:
    """The paper's per-sequence numbers.

    Attributes:
        recall_at_1: fraction in [0, 1].
        f1_max: in [0, 1].
        sr: success rate in [0, 1] (NaN if the method estimates no pose).
        e_r_deg: mean rotation error over successful queries, degrees (NaN if none).
        e_t_m: mean translation error over successful queries, metres (NaN if none or rotation-only).
        n_queries: number of queries (GT).
    """

    recall_at_1: float
    f1_max: float
    sr: float
    e_r_deg: float
    e_t_m: float
    n_queries: int

    def as_dict(self) -> dict[str, float | int]:
        return {
            "recall_at_1": self.recall_at_1,
            "f1_max": self.f1_max,
            "sr": self.sr,
            "e_r_deg": self.e_r_deg,
            "e_t_m": self.e_t_m,
            "n_queries": self.n_queries,
        }


def summarize(
    query_poses: np.ndarray,
    retrieved_xy: np.ndarray,
    top1_distance: np.ndarray,
    database_xy: np.ndarray,
    radius_m: float,
    T_map_query_est: np.ndarray | None = None,
    max_rot_deg: float = MAX_ROTATION_ERROR_DEG,
    rotation_only: bool = False,
    T_map_query_gt: np.ndarray | None = None,
) -> LocalizationMetrics:
    """All metrics for one query sequence against one database.

    Args:
        query_poses: (Q, 3) ground-truth T_map_query (x [m], y [m], yaw [rad]).
        retrieved_xy: (Q, 2) map positions of each query's top-1 keyframe (NaN rows: nothing retrieved).
        top1_distance: (Q,) descriptor distance of the top-1 (for F1max).
        database_xy: (M, 2) map positions of all database keyframes (for true revisits).
        radius_m: R, metres (``radius_for(dataset)``).
        T_map_query_est: (Q, 3) estimated poses (NaN rows where localization failed); None for methods that
            estimate no pose (SR, e_r, e_t are then NaN).
        max_rot_deg: rotation bound of a success, degrees.
        rotation_only: the estimate's translation is meaningless (ReFeree): success = correct retrieval and
            e_r < max_rot_deg; e_t is NaN.
        T_map_query_gt: (Q, 3) ground truth the estimated poses are scored against, when it refers to another
            time than ``query_poses`` (the mid-sweep poses, docs/CONVENTIONS.md); None: ``query_poses``.
    """
    gt = np.asarray(query_poses, dtype=np.float64)
    if gt.ndim != 2 or gt.shape[1] != 3:
        raise ValueError(f"query_poses must be (Q, 3) (x, y, yaw), got shape {gt.shape}")
    correct = retrieval_correct(gt, retrieved_xy, radius_m)
    revisit = has_revisit(gt, database_xy, radius_m)
    r1 = float(correct.mean()) if correct.size else 0.0
    f1 = precision_recall_curve(top1_distance, correct, revisit).f1_max
    sr = e_r_mean = e_t_mean = float("nan")
    if T_map_query_est is not None:
        e_t, e_r = localization_errors(T_map_query_est, gt if T_map_query_gt is None else T_map_query_gt)
        if rotation_only:
            ok = rotation_success(correct, e_r, max_rot_deg)
        else:
            ok = localization_success(e_t, e_r, radius_m, max_rot_deg)
        sr = float(ok.mean()) if ok.size else 0.0
        if ok.any():
            e_r_mean = float(e_r[ok].mean())
            e_t_mean = float("nan") if rotation_only else float(e_t[ok].mean())
    return LocalizationMetrics(r1, f1, sr, e_r_mean, e_t_mean, int(gt.shape[0]))


@dataclass
class RevisitBreakdown:
    """Metrics split by query kind (revisit vs no match); see the module docstring.

    Rates are fractions in [0, 1], NaN where the denominator is 0 or the figure does not apply.

    Attributes:
        n_queries: all queries.
        n_revisit: queries with a database entry within R.
        n_no_match: queries without one (``n_queries - n_revisit``).
        recall_at_1_revisit: correct top-1 / n_revisit (the headline Recall@1).
        recall_at_1_all: correct top-1 / n_queries (the paper's Recall@1).
        sr_revisit: successes among revisit queries / n_revisit (NaN without a success rule).
        sr_all: successes / n_queries (the paper's SR; NaN without a success rule).
        has_rejection: the method can decline to answer (``answered`` was given).
        n_rejected_no_match: no-match queries the method rejected (correct rejections).
        n_wrong_pose_no_match: no-match queries answered with a pose that misses the success rule.
        n_correct_pose_no_match: no-match queries answered with a pose that meets it (possible when a keyframe
            just beyond R still overlaps the query's view).
        correct_rejection_rate: n_rejected_no_match / n_no_match.
        wrong_pose_rate_no_match: n_wrong_pose_no_match / n_no_match.
        n_rejected_revisit: revisit queries the method rejected (missed localizations).
        n_wrong_pose_revisit: revisit queries answered with a pose that misses the success rule.
    """

    n_queries: int
    n_revisit: int
    n_no_match: int
    recall_at_1_revisit: float
    recall_at_1_all: float
    sr_revisit: float
    sr_all: float
    has_rejection: bool
    n_rejected_no_match: int | None
    n_wrong_pose_no_match: int | None
    n_correct_pose_no_match: int | None
    correct_rejection_rate: float
    wrong_pose_rate_no_match: float
    n_rejected_revisit: int | None
    n_wrong_pose_revisit: int | None


def _rate(num: int, den: int) -> float:
    return float(num) / den if den > 0 else float("nan")


def revisit_breakdown(correct: np.ndarray, revisit: np.ndarray, success: np.ndarray | None = None,
                      answered: np.ndarray | None = None) -> RevisitBreakdown:
    """Recall@1 / SR over revisit queries and over all, and the rejection figures on no-match queries.

    Args:
        correct: (Q,) bool, top-1 within R of the query (``retrieval_correct``).
        revisit: (Q,) bool, the database holds an entry within R (``has_revisit``).
        success: (Q,) bool per-query success (``localization_success`` or ``rotation_success``); None for
            methods that estimate neither pose nor heading (SR figures NaN).
        answered: (Q,) bool, the method gave an answer (a pose) rather than rejecting the query; None for
            methods without a rejection rule (they answer every query; the rejection figures are NaN/None).
            An answered query whose ``success`` is False is a wrong pose.

    Raises:
        ValueError: arrays of different lengths, or ``answered`` without ``success``.
    """
    c = np.asarray(correct, dtype=bool).reshape(-1)
    rv = np.asarray(revisit, dtype=bool).reshape(-1)
    ok = None if success is None else np.asarray(success, dtype=bool).reshape(-1)
    ans = None if answered is None else np.asarray(answered, dtype=bool).reshape(-1)
    for name, a in (("revisit", rv), ("success", ok), ("answered", ans)):
        if a is not None and a.shape != c.shape:
            raise ValueError(f"correct {c.shape} and {name} {a.shape} differ in length")
    if ans is not None and ok is None:
        raise ValueError("answered needs success: a rejection rule only makes sense with a success rule")
    q, n_rev = int(c.size), int(rv.sum())
    nm = ~rv
    n_nm = q - n_rev
    sr_rev = sr_all = float("nan")
    if ok is not None:
        sr_rev = _rate(int((ok & rv).sum()), n_rev)
        sr_all = _rate(int(ok.sum()), q)
    rej_nm = wrong_nm = good_nm = rej_rv = wrong_rv = None
    cr = wr = float("nan")
    if ans is not None and ok is not None:
        rej_nm = int((~ans & nm).sum())
        wrong_nm = int((ans & ~ok & nm).sum())
        good_nm = int((ans & ok & nm).sum())
        rej_rv = int((~ans & rv).sum())
        wrong_rv = int((ans & ~ok & rv).sum())
        cr, wr = _rate(rej_nm, n_nm), _rate(wrong_nm, n_nm)
    return RevisitBreakdown(q, n_rev, n_nm, _rate(int((c & rv).sum()), n_rev), _rate(int(c.sum()), q),
                            sr_rev, sr_all, ans is not None, rej_nm, wrong_nm, good_nm, cr, wr, rej_rv, wrong_rv)


def proportion_interval(successes: int, trials: int, level: float = 0.95) -> tuple[float, float]:
    """Wilson score interval (fractions) of a rate ``successes / trials`` (``scipy.stats.binomtest``).

    How far a Recall@1 or SR measured on ``trials`` queries may lie from the rate the method would reach on many
    more queries like them: with 232-517 revisit queries per simulated sequence, 1.5-4 points either side
    at 85-95 %. (NaN, NaN) when ``trials`` is 0.
    """
    if trials <= 0:
        return float("nan"), float("nan")
    from scipy.stats import binomtest  # scipy, imported where used (as ``has_revisit``'s KD-tree)

    ci = binomtest(int(successes), int(trials)).proportion_ci(confidence_level=level, method="wilson")
    return float(ci.low), float(ci.high)
