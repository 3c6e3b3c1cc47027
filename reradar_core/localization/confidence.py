"""Calibrated confidence of a localization answer: P(pose within the success thresholds | cues).

The aligned-landmark ratio alone is not a probability: a wrong place can align half of the query's landmarks
(the best of 20-60 screened candidates is chosen), and a right place in snow may align less. The confidence
combines several cues of one answer (``ConfidenceCues``, computed from the winner and the screened
candidates by ``confidence_cues``) in a logistic regression on standardised cues (``ConfidenceModel``):

    p = sigmoid(intercept + coef . (cues - mean) / scale)

``p`` estimates the probability that the answer's map pose lies within the paper's success thresholds
(``reradar_core.evaluation``: translation error below the radius R - 20 m urban, 25 m off-road - and heading
error below 10 deg). The coefficients are fitted on training-split queries only (``reradar fit-confidence``,
``reradar_core.localization.confidence_fit``) and shipped as a small versioned JSON
(``confidence_model.json`` next to this module). Inference is a numpy dot product.

Cues (one answer; the winner = the verified candidate with the most inliers):

- ``aligned_ratio``: the winner's inliers / query landmarks (the old decision score), in [0, 1].
- ``log_aligned``: log(1 + number of aligned query landmarks).
- ``margin``: the winner's screen score minus the best screen score among candidates at a *different place*
  (keyframe farther than ``place_radius_m`` from the answer's map position); the winner's score when there is
  none. Screen scores are all on one scale (fraction of query landmarks aligned by the cheap screen); a
  candidate without one (not screened) uses its inlier ratio.
- ``descriptor_distance``: the winner's Euclidean distance between unit global descriptors, in [0, 2].
- ``spread_m``: spatial spread of the aligned landmarks: sqrt of the smaller eigenvalue of their (2, 2)
  covariance in the query's sensor frame, metres (landmarks along one façade constrain the pose badly).
- ``agreement``: fraction of the best other candidates (top ``top_n`` by score) whose keyframe lies within
  ``place_radius_m`` of the answer's map position: neighbours of the right keyframe align well too.
- ``ambiguity``: the pose estimator's best rival pose's alignment score / the answer's (0 = unique, 1 = tie;
  clipped to [0, 2]; 0 where not computed).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from reradar_core.errors import ConfigError
from reradar_core.geometry.se2 import compose

if TYPE_CHECKING:  # the pipeline imports this module; types only
    from reradar_core.localization.pipeline import CandidateVerification, LocalizationResult

__all__ = [
    "CUE_NAMES",
    "CONFIDENCE_FORMAT_VERSION",
    "DEFAULT_MODEL_PATH",
    "ConfidenceCues",
    "ConfidenceModel",
    "landmark_spread_m",
    "candidate_score",
    "confidence_cues",
    "cues_from_result",
    "COMPETITION_CUES",
    "tracked_cues",
    "fit_confidence_model",
    "default_confidence_model",
    "reliability_bins",
    "expected_calibration_error",
    "choose_min_confidence",
    "choose_min_confidence_by_cost",
]

#: order of the cues in a cue vector (and in the JSON's arrays)
CUE_NAMES: tuple[str, ...] = ("aligned_ratio", "log_aligned", "margin", "descriptor_distance", "spread_m",
                              "agreement", "ambiguity")
#: version of the JSON layout (bumped when the cue definitions or the file's fields change)
CONFIDENCE_FORMAT_VERSION = 1
#: the shipped model (written by ``reradar fit-confidence``)
DEFAULT_MODEL_PATH = Path(__file__).resolve().parent / "confidence_model.json"
_MAX_SPREAD_M = 100.0
_MAX_AMBIGUITY = 2.0


@dataclass(frozen=True)
class ConfidenceCues:
    """The cues of one answer (definitions in the module docstring); all finite floats."""

    aligned_ratio: float
    log_aligned: float
    margin: float
    descriptor_distance: float
    spread_m: float
    agreement: float
    ambiguity: float

    def as_array(self) -> np.ndarray:
        """(len(CUE_NAMES),) float64 in ``CUE_NAMES`` order."""
        return np.array([getattr(self, n) for n in CUE_NAMES], dtype=np.float64)

    def as_dict(self) -> dict[str, float]:
        return {n: float(getattr(self, n)) for n in CUE_NAMES}


def landmark_spread_m(points_xy_m: np.ndarray) -> float:
    """Spatial spread of a landmark set: sqrt of the smaller eigenvalue of its (2, 2) covariance, metres.

    Args:
        points_xy_m: (K, 2) landmark positions, metres (any one frame).

    Returns:
        The spread (0 for fewer than 3 points): small when the landmarks lie along one line.
    """
    pts = np.asarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
    if len(pts) < 3:
        return 0.0
    cov = np.cov(pts, rowvar=False)
    return float(math.sqrt(max(float(np.linalg.eigvalsh(cov)[0]), 0.0)))


def candidate_score(c: CandidateVerification) -> float:
    """How well ``c`` aligned: its screen score, or its verified inlier ratio when it was not screened."""
    return float(c.screen_score) if c.screen_score is not None else float(c.inlier_ratio)


def confidence_cues(best: CandidateVerification | None, candidates: Sequence[CandidateVerification],
                    place_radius_m: float = 20.0, top_n: int = 5) -> ConfidenceCues | None:
    """Cues of an answer from its winner and the screened candidates.

    Args:
        best: the winner (its ``T_keyframe_query`` is the answer); None = no answer.
        candidates: every screened / verified candidate (the winner included; identified by ``rank``).
        place_radius_m: a candidate whose keyframe lies farther than this from the answer's map position is
            at a different place (margin), one within it agrees (agreement), metres.
        top_n: how many of the best other candidates the agreement looks at.

    Returns:
        ``ConfidenceCues``, or None when there is no pose to judge (no winner, or its fit failed).
    """
    if best is None or best.T_keyframe_query is None:
        return None
    T_map_query = np.asarray(compose(best.T_map_keyframe, best.T_keyframe_query), np.float64)
    others = [c for c in candidates if c.rank != best.rank]
    if others:
        xy = np.array([np.asarray(c.T_map_keyframe, np.float64)[:2] for c in others])
        dist = np.hypot(xy[:, 0] - T_map_query[0], xy[:, 1] - T_map_query[1])
        scores = np.array([candidate_score(c) for c in others])
        far = dist > place_radius_m
        rival = float(scores[far].max()) if far.any() else 0.0
        top = np.argsort(-scores, kind="stable")[:top_n]
        agreement = float(np.mean(dist[top] <= place_radius_m))
    else:
        rival, agreement = 0.0, 0.0
    amb = float(best.ambiguity) if best.ambiguity is not None and math.isfinite(best.ambiguity) else (
        _MAX_AMBIGUITY if best.ambiguity is not None and math.isinf(best.ambiguity) else 0.0)
    spread = float(best.inlier_spread_m) if best.inlier_spread_m is not None and math.isfinite(
        best.inlier_spread_m) else 0.0
    return ConfidenceCues(
        aligned_ratio=float(best.inlier_ratio),
        log_aligned=float(math.log1p(max(best.num_inliers, 0))),
        margin=candidate_score(best) - rival,
        descriptor_distance=float(best.descriptor_distance),
        spread_m=min(spread, _MAX_SPREAD_M),
        agreement=agreement,
        ambiguity=min(max(amb, 0.0), _MAX_AMBIGUITY),
    )


#: the cues that describe the competition between places and poses (``margin``: other places; ``agreement``: the
#: best other candidates; ``ambiguity``: rival poses of the hypothesis search), which a registration from a prior
#: never looks at (``tracked_cues``)
COMPETITION_CUES = ("margin", "agreement", "ambiguity")


def tracked_cues(cues: ConfidenceCues, model: ConfidenceModel) -> ConfidenceCues:
    """The cues of a tracked answer (``Localizer.track``): ``cues`` with the ``COMPETITION_CUES`` at ``model``'s
    training means (standardised 0: they then move the confidence neither way).

    A registration from a prior looks only at the keyframes next to the prior and never searches for rival poses,
    so computed as for a global answer these cues read best-case (no candidate at another place: the whole score
    as margin; the prior's neighbour agrees; no rival pose: ambiguity 0), whatever the scan shows. With them a
    registration drawn 1.9 m / 4.7 degrees off a prior 0.2 m from the truth by a partly changed scene, aligning 38 %
    of the landmarks, scored 0.988 and was tracked on, 2-6 m off, at 0.96-0.9998 (QA, session 23), where the global
    answer for the same scans is refused (margin 0-0.05, ambiguity 0.8-0.98). What a tracked answer does measure
    (aligned landmarks, their spread, the descriptor distance) then decides."""
    values = cues.as_dict()
    for name in COMPETITION_CUES:
        values[name] = float(model.mean[CUE_NAMES.index(name)])
    return ConfidenceCues(**values)


def cues_from_result(result: LocalizationResult, place_radius_m: float = 20.0,
                     top_n: int = 5) -> ConfidenceCues | None:
    """``confidence_cues`` of a ``LocalizationResult`` (its ``best`` and ``candidates``)."""
    return confidence_cues(result.best, result.candidates, place_radius_m, top_n)


def _sigmoid(z: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * z))  # overflow-free logistic


@dataclass(frozen=True)
class ConfidenceModel:
    """Logistic regression on standardised cues.

    Attributes:
        cue_names: the cue order of ``mean``/``scale``/``coef`` (must equal ``CUE_NAMES``).
        mean, scale: (C,) float64 standardisation (scale > 0).
        coef: (C,) float64 weights on the standardised cues; intercept: the bias.
        min_confidence: the decision bar recommended with these coefficients (chosen at fit time on the
            training split; ``LocalizationConfig.min_confidence`` None uses it), in [0, 1].
        place_radius_m: the cues' place radius (``confidence_cues``), metres; top_n: their agreement count.
        min_aligned_ratio: the aligned-landmark floor fitted with these coefficients (the share of the query's
            landmarks the winner must align before the confidence is asked; ``LocalizationConfig``'s
            ``min_inlier_ratio`` None uses it with the ``guided`` estimator), in [0, 1]. Chosen at fit time on
            the training splits' sessions that train no weights; 0.5 in models fitted before it existed.
        meta: provenance (command, data, sizes, calibration figures); informational.
    """

    cue_names: tuple[str, ...]
    mean: np.ndarray
    scale: np.ndarray
    coef: np.ndarray
    intercept: float
    min_confidence: float = 0.5
    place_radius_m: float = 20.0
    top_n: int = 5
    min_aligned_ratio: float = 0.5
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if tuple(self.cue_names) != CUE_NAMES:
            raise ConfigError(f"confidence model cues {list(self.cue_names)} differ from this version's "
                              f"{list(CUE_NAMES)}; re-fit it with `reradar fit-confidence`")
        c = len(CUE_NAMES)
        for name in ("mean", "scale", "coef"):
            arr = np.asarray(getattr(self, name), dtype=np.float64)
            if arr.shape != (c,) or not np.all(np.isfinite(arr)):
                raise ConfigError(f"confidence model {name} must be {c} finite numbers, got shape {arr.shape}")
            object.__setattr__(self, name, arr)
        if np.any(self.scale <= 0):
            raise ConfigError("confidence model scale must be > 0")
        if not math.isfinite(self.intercept) or not 0.0 <= self.min_confidence <= 1.0:
            raise ConfigError("confidence model intercept must be finite and min_confidence in [0, 1]")
        if not 0.0 <= self.min_aligned_ratio <= 1.0:
            raise ConfigError(f"confidence model min_aligned_ratio must be in [0, 1], got {self.min_aligned_ratio}")

    def predict(self, cues: ConfidenceCues | np.ndarray) -> Any:
        """Probability that the pose is within the success thresholds.

        Args:
            cues: one ``ConfidenceCues``, or a (C,) / (Q, C) float array in ``CUE_NAMES`` order.

        Returns:
            A float in [0, 1] for one answer, else (Q,) float64.
        """
        x = cues.as_array() if isinstance(cues, ConfidenceCues) else np.asarray(cues, dtype=np.float64)
        z = ((x - self.mean) / self.scale) @ self.coef + self.intercept
        p = _sigmoid(np.asarray(z, dtype=np.float64))
        return float(p) if p.ndim == 0 else p

    def to_dict(self) -> dict[str, Any]:
        return {"format_version": CONFIDENCE_FORMAT_VERSION, "cue_names": list(self.cue_names),
                "mean": self.mean.tolist(), "scale": self.scale.tolist(), "coef": self.coef.tolist(),
                "intercept": float(self.intercept), "min_confidence": float(self.min_confidence),
                "place_radius_m": float(self.place_radius_m), "top_n": int(self.top_n),
                "min_aligned_ratio": float(self.min_aligned_ratio), "meta": self.meta}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ConfidenceModel:
        if d.get("format_version") != CONFIDENCE_FORMAT_VERSION:
            raise ConfigError(f"confidence model format {d.get('format_version')!r} is not the supported "
                              f"{CONFIDENCE_FORMAT_VERSION}; re-fit it with `reradar fit-confidence`")
        try:
            return cls(tuple(d["cue_names"]), np.asarray(d["mean"]), np.asarray(d["scale"]),
                       np.asarray(d["coef"]), float(d["intercept"]), float(d["min_confidence"]),
                       float(d["place_radius_m"]), int(d["top_n"]),
                       # absent in files fitted before the floor was fitted: the fixed floor of then
                       float(d.get("min_aligned_ratio", 0.5)), dict(d.get("meta", {})))
        except KeyError as exc:
            raise ConfigError(f"confidence model JSON lacks the field {exc}") from None

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=2, sort_keys=True) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> ConfidenceModel:
        p = Path(path)
        if not p.is_file():
            raise ConfigError(f"confidence model {p.name} not found; fit one with `reradar fit-confidence`")
        return cls.from_dict(json.loads(p.read_text()))


@lru_cache(maxsize=1)
def default_confidence_model() -> ConfidenceModel:
    """The shipped model (``confidence_model.json`` next to this module), read once."""
    return ConfidenceModel.load(DEFAULT_MODEL_PATH)


def fit_confidence_model(x: np.ndarray, y: np.ndarray, l2: float = 1.0, min_confidence: float = 0.5,
                         place_radius_m: float = 20.0, top_n: int = 5,
                         meta: dict[str, Any] | None = None) -> ConfidenceModel:
    """Fit the logistic regression by maximum likelihood with an L2 penalty (scipy L-BFGS; deterministic).

    Args:
        x: (Q, C) cues in ``CUE_NAMES`` order; y: (Q,) bool / 0-1 labels (1 = pose within the thresholds).
        l2: penalty on the standardised weights (not on the intercept), as 0.5 * l2 * |w|^2 added to the
            summed negative log-likelihood.
        min_confidence, place_radius_m, top_n, meta: stored with the coefficients.

    Raises:
        ConfigError: shapes differ, too few samples, or a single class.
    """
    from scipy.optimize import minimize

    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64).reshape(-1)
    if x.ndim != 2 or x.shape[1] != len(CUE_NAMES) or x.shape[0] != y.shape[0]:
        raise ConfigError(f"cues must be (Q, {len(CUE_NAMES)}) with Q labels, got {x.shape} and {y.shape}")
    if len(y) < 2 or y.min() == y.max():
        raise ConfigError("fitting a confidence model needs both correct and wrong answers")
    mean = x.mean(axis=0)
    scale = x.std(axis=0)
    scale = np.where(scale > 1e-9, scale, 1.0)  # a constant cue gets weight ~0 through the penalty
    xs = (x - mean) / scale
    a = np.hstack([xs, np.ones((len(xs), 1))])

    def loss(w: np.ndarray) -> tuple[float, np.ndarray]:
        z = a @ w
        # sum log(1 + e^z) - y z, stable form
        nll = float(np.sum(np.logaddexp(0.0, z) - y * z)) + 0.5 * l2 * float(w[:-1] @ w[:-1])
        g = a.T @ (_sigmoid(z) - y)
        g[:-1] += l2 * w[:-1]
        return nll, g

    res = minimize(loss, np.zeros(a.shape[1]), jac=True, method="L-BFGS-B", options={"maxiter": 1000})
    w = np.asarray(res.x, dtype=np.float64)
    return ConfidenceModel(CUE_NAMES, mean, scale, w[:-1], float(w[-1]), min_confidence=min_confidence,
                           place_radius_m=place_radius_m, top_n=top_n, meta=dict(meta or {}))


def reliability_bins(p: np.ndarray, y: np.ndarray, bins: int = 10) -> dict[str, np.ndarray]:
    """Reliability table over equal-width probability bins.

    Returns:
        ``edges`` (bins + 1,), per bin ``count`` (int), ``mean_p`` (mean predicted probability) and
        ``frac_pos`` (observed fraction of correct answers); NaN for empty bins.
    """
    p = np.asarray(p, dtype=np.float64).reshape(-1)
    y = np.asarray(y, dtype=np.float64).reshape(-1)
    edges = np.linspace(0.0, 1.0, bins + 1)
    idx = np.clip(np.digitize(p, edges[1:-1]), 0, bins - 1)
    count = np.bincount(idx, minlength=bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_p = np.bincount(idx, weights=p, minlength=bins) / count
        frac = np.bincount(idx, weights=y, minlength=bins) / count
    return {"edges": edges, "count": count, "mean_p": mean_p, "frac_pos": frac}


def expected_calibration_error(p: np.ndarray, y: np.ndarray, bins: int = 10) -> float:
    """ECE = sum over bins of (bin count / Q) * |observed fraction - mean predicted probability|, in [0, 1]."""
    t = reliability_bins(p, y, bins)
    n = int(t["count"].sum())
    if n == 0:
        return 0.0
    ok = t["count"] > 0
    return float(np.sum(t["count"][ok] / n * np.abs(t["frac_pos"][ok] - t["mean_p"][ok])))


def choose_min_confidence(p: np.ndarray, correct: np.ndarray, eligible: np.ndarray, num_queries: int,
                          max_wrong_fraction: float = 0.005) -> float:
    """The lowest bar on ``p`` at which wrong answers are at most ``max_wrong_fraction`` of all queries.

    Args:
        p: (Q,) confidence of each answer; correct: (Q,) bool pose within the thresholds;
        eligible: (Q,) bool the answer passes the other checks (the aligned-ratio floor) - only those can be
            answered ``localized``.
        num_queries: the denominator (all queries, also those without an answer).
        max_wrong_fraction: the allowed share of wrong ``localized`` answers.

    Returns:
        The bar in [0, 1] (a candidate value is one of the ``p`` of eligible answers; 1.0 when even the
        highest confidence would break the limit).
    """
    p = np.asarray(p, dtype=np.float64)
    correct = np.asarray(correct, dtype=bool)
    eligible = np.asarray(eligible, dtype=bool)
    allowed = math.floor(max_wrong_fraction * num_queries + 1e-9)
    wrong_p = np.sort(p[eligible & ~correct])[::-1]  # descending
    if len(wrong_p) <= allowed:
        return 0.0
    # answering p >= bar admits every wrong answer with p >= bar: the bar must exceed the (allowed+1)-th highest
    bar = float(np.nextafter(wrong_p[allowed], np.inf))
    return min(bar, 1.0)


def choose_min_confidence_by_cost(p: np.ndarray, correct: np.ndarray, eligible: np.ndarray,
                                  wrong_cost: float = 10.0) -> float:
    """The bar on ``p`` that minimises ``wrong_cost`` x wrong answers + refused correct answers.

    Only eligible answers (past the aligned-ratio floor) can be ``localized``; answering ``p >= bar`` admits
    every eligible answer at or above the bar and refuses the rest. Ties go to the lowest bar (fewest
    refusals).

    Args:
        p: (Q,) confidence of each answer; correct: (Q,) bool pose within the thresholds;
        eligible: (Q,) bool the answer passes the floor.
        wrong_cost: what one wrong ``localized`` answer costs, in refused correct answers (> 0).

    Returns:
        The bar in [0, 1] (0.0, or just above one of the eligible answers' ``p``).
    """
    if wrong_cost <= 0:
        raise ConfigError(f"wrong_cost must be positive, got {wrong_cost}")
    p = np.asarray(p, dtype=np.float64)
    el = np.asarray(eligible, dtype=bool)
    ok = np.asarray(correct, dtype=bool)[el]
    pe = p[el]
    order = np.argsort(pe, kind="stable")
    pe, ok = pe[order], ok[order]
    # bar k refuses the k lowest answers: refused correct = cumsum(ok)[k-1], admitted wrong = wrong total - ...
    refused_correct = np.concatenate([[0], np.cumsum(ok)])
    admitted_wrong = int((~ok).sum()) - np.concatenate([[0], np.cumsum(~ok)])
    cost = wrong_cost * admitted_wrong + refused_correct
    # only cut between distinct values (equal p cannot be separated by a bar)
    valid = np.ones(len(pe) + 1, dtype=bool)
    valid[1:-1] = pe[1:] > pe[:-1]
    k = int(np.flatnonzero(valid)[np.argmin(cost[valid])])
    if k == 0:
        return 0.0
    return min(float(np.nextafter(pe[k - 1], np.inf)), 1.0)
