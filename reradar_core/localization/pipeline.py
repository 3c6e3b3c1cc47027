"""Global localization of one query scan against retrieved map keyframes (paper Sec. III, pose estimation).

Pipeline: the caller (``Localizer``) retrieves the top-k keyframes by global descriptor. With the default
``guided`` pose method every candidate is first screened by a cheap landmark-alignment score
(``screen_alignment``; further blocks of ``top_k`` up to ``max_candidates`` while none aligns well) and the best
``verify_k`` are verified in full (``estimate_pose_guided``); with
``mutual_nn`` every candidate is verified by mutual-nearest-neighbour matching of local descriptors and a
RANSAC 2-D rigid fit. The verified candidate with the most inliers wins (geometric re-ranking) and the
absolute pose is ``T_map_query = compose(T_map_keyframe, T_keyframe_query)``. A query is reported ``localized`` only when
the winner has at least ``min_inliers`` inliers and ``min_inlier_ratio`` (the floor) and, with ``guided``, its
calibrated ``confidence`` (``localization.confidence``) reaches ``min_confidence`` - an unknown place must not be
reported as localized.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from typing import Literal, Protocol

import numpy as np

from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.se2 import compose, inverse
from reradar_core.localization.confidence import (
    ConfidenceCues,
    ConfidenceModel,
    candidate_score,
    confidence_cues,
    default_confidence_model,
    landmark_spread_m,
)
from reradar_core.localization.screening import ScreenKeyframe, screen_candidates, screen_keyframe
from reradar_core.localization.tracking import TrackingConfig
from reradar_core.matching import (
    AlignmentConfig,
    LandmarkGrid,
    RansacConfig,
    build_landmark_grid,
    count_aligned,
    estimate_pose_guided,
    estimate_rigid_2d,
    match_descriptors,
)
from reradar_core.matching.motion import MotionConfig
from reradar_core.matching.uncertainty import PoseCovarianceConfig

__all__ = [
    "LocalizationConfig",
    "Candidate",
    "CandidateVerification",
    "LocalizationResult",
    "verify_candidate",
    "localize",
    "REASON_NO_CANDIDATE",
    "REASON_TOO_FEW_INLIERS",
    "REASON_SCREENED_OUT",
    "REASON_AMBIGUOUS",
    "REASON_LOW_CONFIDENCE",
    "answer_confidence",
]

logger = logging.getLogger(__name__)

REASON_NO_CANDIDATE = "no_candidate"
REASON_TOO_FEW_INLIERS = "too_few_inliers"
REASON_TOO_FEW_MATCHES = "too_few_matches"
REASON_SCREENED_OUT = "screened_out"
#: The pose estimator found a rival pose aligning as many landmarks (``matching.alignment``): a guess.
REASON_AMBIGUOUS = "ambiguous"
REASON_INCONSISTENT = "inconsistent_with_prior"
REASON_LOW_CONFIDENCE = "low_confidence"

Status = Literal["localized", "not_localized"]
PoseMethod = Literal["guided", "mutual_nn"]


@dataclass(frozen=True)
class LocalizationConfig:
    """Localization settings.

    Attributes:
        top_k: keyframes retrieved by global descriptor and checked geometrically (default 10). With
            ``guided`` they are all screened and the best ``verify_k`` verified in full. With the descriptors
            of before learned whitening the landmark screen had to rank 20 (on boreas-sim Recall@1 after
            re-ranking was 0.61 with 20 screened / 3 verified, 0.69 with 40 / 3); with the learned-whitening
            models 10 screened / 2 verified give the same correct answers on the training splits as 20 / 3
            (1,238 of 1,642 runs, every 2nd query), 1 wrong answer fewer, and 30 % less localization time
            (docs/BENCHMARKS.md, "Learned whitening, ten candidates, one deeper round").
        verify_k: screened candidates verified in full by the ``guided`` estimator (default 1 since session 18;
            2 before). With the width-0.5 descriptors the best-screened candidate is the right one nearly always: on
            the training splits (every 2nd query of every session, each split's own model, 5,818 runs) 1 instead of
            2 gave 3,887 correct / 0 wrong / 25 revisits refused against 3,889 / 0 / 23, and with ``our-3-boreas-w05``
            on the other domains' splits (4,593 runs) 2,761 / 2 / 32 against 2,762 / 2 / 31, for 17-18 % less
            localization time (docs/BENCHMARKS.md, "Session 18"). Expansion rounds verify ``verify_k`` more.
        max_candidates / expand_below_screen_score: ``guided`` only: while no screened candidate aligns at
            least ``expand_below_screen_score`` (0.6) of the query's landmarks, the next ``expansion_block``
            retrieved candidates are screened too, up to ``max_candidates`` (60; callers retrieve that many,
            features are loaded lazily). Confident queries stop after ``top_k``; on offroad-sim every query the
            20-candidate settings missed had its right keyframe at retrieval rank 21-56 and a best screen score
            <= 0.59. ``max_candidates <= top_k`` disables the expansion.
        expand_on_refusal: ``guided`` only: when the answer over the screened candidates is refused (floor,
            ambiguity or confidence), the next ``expansion_block`` retrieved candidates are screened and the
            best ``verify_k`` of them not yet verified are verified, and the decision is taken again over all
            of them, up to ``max_candidates``. Only refused queries pay for it. On the Boreas snow-cover drive
            25 of the 31 revisit queries the pipeline got wrong had their right keyframe outside the 20
            screened (retrieval rank 20-320) while a wrong one screened >= 0.6, so the score-based expansion
            never ran.
        expansion_block: candidates screened per expansion round (both expansions above); None (default) =
            all the rest up to ``max_candidates`` in one round: one batched screen instead of up to five (each
            screen call has a fixed cost), and a refused query pays at most one more screen and ``verify_k``
            more verifications, which bounds the tail latency; ``top_k`` gives the former rounds of ``top_k``.
        stop_verify_ratio: ``guided`` only: the screened candidates are verified best-screened first, and the
            rest are skipped once one aligns at least this fraction of the query's landmarks (None: verify all
            ``verify_k``); the skipped ones keep reason ``screened_out``. Default 0.7: on the boreas-sim
            snow-cover and falling-snow drives (517 queries each, 560-keyframe map, our-3-boreas) it left success
            and wrong poses unchanged (328 / 10 and 317 / 20) and cut pose-estimation time ~12 %; 0.5 (the
            ``localized`` bar) saved 35 % but cost 2 successes and added 2 wrong poses on falling snow, 0.6 one
            each (docs/BENCHMARKS.md).
        min_inliers: inliers the best candidate needs to count as localized (``guided``: query landmarks
            within 0.75 m of a keyframe landmark after the fit; ``mutual_nn``: RANSAC inliers under 2 m).
            Unrelated scans rarely agree on more than a handful of points, so 12 rejects unknown places while
            real revisits have tens to hundreds.
        min_inlier_ratio: minimum inlier ratio of the winner (the floor: inliers / query landmarks) before the
            confidence is asked; None = the method's default: ``guided`` the floor fitted with the shipped
            confidence model (``ConfidenceModel.min_aligned_ratio``, chosen by ``reradar fit-confidence`` on
            the training splits' sessions that train no weights, docs/MODEL.md "Confidence"; 0.50 before,
            a value once read off boreas-sim queries, where the floor alone had to keep wrong winners out);
            ``mutual_nn``: 0 (inliers / matches, disabled).
        match_ratio: optional Lowe ratio for descriptor matching (None: mutual nearest neighbours only).
        rerank: True = choose the verified candidate with the most inliers (geometric re-ranking);
            False = verify only the top-1 retrieval (plain retrieval, for comparison).
        pose_method: ``guided`` (default): descriptor-guided hypotheses scored by whole-landmark alignment
            and refined by nearest-landmark association (``reradar_core.matching.alignment``; inliers are
            query landmarks within 0.75 m of a keyframe landmark); ``mutual_nn``: the paper's mutual
            nearest-neighbour matching + RANSAC over the matches (inliers are matches). See
            docs/BENCHMARKS.md for what each gives.
        alignment: settings of the guided estimator (its own ``min_inliers`` is replaced by this config's).
        ransac: RANSAC settings of ``mutual_nn`` (threshold in metres, iterations, seed).
        tracking: settings of tracking mode (``Localizer.track``; ``localization.tracking``).
        motion: motion compensation of a localized answer's pose (``Localizer``; ``matching.motion``: both scans
            de-skewed, the query's motion fitted with its pose; the decision, confidence and cues are the rigid
            registration's). ``MotionConfig(enabled=False)``: the rigid pose, as before session 29.
        covariance: a localized answer's pose covariance (``Localizer``; ``matching.uncertainty``: the final
            registration's landmark pairs, scaled by factors fitted on the training splits; ``LocalizationResult.
            pose_covariance``). ``PoseCovarianceConfig(enabled=False)``: none.
        min_confidence: ``guided`` only: an answer that passes the checks above is ``localized`` only when its
            confidence (``reradar_core.localization.confidence``: calibrated probability that the pose is
            within the success thresholds) reaches this bar; the aligned-ratio bar stays as a floor. None =
            the bar stored with the shipped confidence model (chosen at fit time on the training splits: wrong
            answers <= 0.5 % of every split's queries and the least 10 x wrong + refused-correct cost,
            docs/MODEL.md "Confidence"); 0 = the floor alone (the decision before the confidence).
        prescreen_keep / prescreen_source_points / prescreen_hypotheses: ``guided`` only: an expansion round
            (either expansion above) of more than ``prescreen_keep`` (5) candidates is first screened coarsely,
            pairing every (N // ``prescreen_source_points``)-th of the N query landmarks by descriptor (64; the
            full screen 256) and drawing ``prescreen_hypotheses`` (1,000 of the full screen's 1,500) minimal sets
            (``prescreen_alignment``), and only its best ``prescreen_keep`` by that score are screened in full;
            the others keep the coarse score as their ``screen_score``. The first ``top_k`` are always screened
            in full. None = every candidate in full (before). Chosen on the training splits (never a benchmark
            query; docs/BENCHMARKS.md "Session 9"): most deep rounds are queries with no map keyframe near, which
            the full screen of ~50 candidates made 3-4x as slow as a confident query.
        min_place_margin / place_margin_radius_m: the winner must out-screen every candidate at a different place
            (keyframe farther than ``place_margin_radius_m``, 20 m, from the answer) by at least this fraction of the
            query's landmarks, else the answer is ``ambiguous`` (None: no such rule). Two places that fit the scan
            equally well are an unknown place, never a guess: the confidence's margin cue weighs such a tie, but
            a map with one drive at two positions (two GNSS offsets, look-alike streets) still gave ties answered
            at confidence 0.9998, 500 m off (QA, session 21). Default 0.075 since session 26, chosen by ``reradar
            fit-confidence`` (``confidence_fit.choose_place_margin``: the widest margin that refuses at most 0.5 % of
            the right answers of the training splits' unseen sessions, 12 of 2,582, while on their streets rebuilt
            as periodic worlds it leaves 29 of 193 wrong answers one period off; docs/MODEL.md "Periodic streets";
            ``test_shipped_place_margin_is_the_fitted_one``); 0.02 until then (session 21, docs/BENCHMARKS.md
            "Session 21"). The tracking checks use it too. A radius of 15 m / 10 m refused 7 / 72 correct answers more; at 20 m a
            copy of the place 21-25 m away is not a rival for every keyframe, so 2-5 of the 8 demo queries on a map
            holding the demo drive twice 21-25 m apart were still answered on the wrong copy (QA re-test).
        max_place_repetition / repetition_rivals / repetition_neighbours / repetition_verify: ``Localizer`` and
            ``guided`` only (global answers; a tracked one rests on its prior; the bar was chosen for the guided
            estimate): an answer whose winning keyframe's place repeats on the map is ``ambiguous``. A keyframe's
            repetition (``localization.repetition``) is localized like a query: its aligned ratio against the
            best-screened of its ``repetition_neighbours`` (4) nearest keyframes within ``place_margin_radius_m`` is
            the reference; among the first ``repetition_rivals`` (20) keyframes retrieved for it that lie farther
            (the retrieval reaches past the keyframes within the radius), the ``repetition_verify`` (3)
            best-screened are verified, and one whose pose puts the keyframe at another place (farther than the
            radius from where it is), aligning at least the answers' floor (``effective_min_inlier_ratio``) and
            ``max_place_repetition`` (0.95) of the reference or more, marks it (None: no such rule). 0.95 since session 27, chosen on
            training data by the tie margin's rule (``benchmarks/place_repetition.py``; docs/MODEL.md "Repeated
            places"): of 0.70-1.10 in steps of 0.05, those that refuse at most 0.5 % of the right answers of the
            training splits' unseen sessions on their pairing maps (every scan a keyframe, and keyframes 12 m
            apart; 0.90: 10 of 5,055, 0.85: 30), and of those the largest that leaves the fewest wrong answers
            among the same splits' periodic worlds' runs (76 wrong with the tie margin alone, 2 at 0.90 and 0.95,
            8 at 1.0; the held-out tails 14 -> 0). Computed once per keyframe (~20-40 ms) and cached by the
            ``Localizer``. A keyframe with no other keyframe within the radius (a map sparser than 20 m) is not
            judged.
        verify_ties: ``guided`` only: screened candidates whose score lies within ``min_place_margin`` of the best
            one's are verified too, at most this many beyond ``verify_k`` (0: off). Keyframes a few metres apart
            screen alike, and the order among them is chance: a reversed drive's scan screened 0.664 on a keyframe
            11 m away and on one 1 m away, the first was verified alone and answered 10 m off along the road at
            confidence 0.9998 (QA, session 24); verified, the near one aligns more landmarks and wins.
    """

    top_k: int = 10
    verify_k: int = 1
    max_candidates: int = 60
    expand_below_screen_score: float = 0.6
    expand_on_refusal: bool = True
    expansion_block: int | None = None
    stop_verify_ratio: float | None = 0.7
    min_inliers: int = 12
    min_inlier_ratio: float | None = None
    match_ratio: float | None = None
    rerank: bool = True
    pose_method: PoseMethod = "guided"
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    ransac: RansacConfig = field(default_factory=RansacConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    covariance: PoseCovarianceConfig = field(default_factory=PoseCovarianceConfig)
    min_confidence: float | None = None
    prescreen_keep: int | None = 5
    prescreen_source_points: int = 64
    prescreen_hypotheses: int = 1000
    min_place_margin: float | None = 0.075
    place_margin_radius_m: float = 20.0
    verify_ties: int = 3
    max_place_repetition: float | None = 0.95
    repetition_rivals: int = 20
    repetition_neighbours: int = 4
    repetition_verify: int = 3

    @property
    def prescreen_alignment(self) -> AlignmentConfig:
        """The coarse screen's settings: ``alignment`` with ``prescreen_source_points`` source landmarks and
        ``prescreen_hypotheses`` minimal sets."""
        return replace(self.alignment, screen_source_points=self.prescreen_source_points,
                       screen_hypotheses=self.prescreen_hypotheses)

    def margin_landmarks(self, num_landmarks: int) -> float:
        """``min_place_margin`` of a query with ``num_landmarks`` landmarks, in landmarks (0 without the rule): how
        many more an answer must align than a rival place, pose, reversal or turn before it is not a tie."""
        return (self.min_place_margin or 0.0) * num_landmarks

    @property
    def num_to_retrieve(self) -> int:
        """How many keyframes a caller should retrieve: ``max_candidates`` for ``guided`` (the expansion may
        screen that many), else ``top_k``."""
        if self.pose_method == "guided" and self.rerank:
            return max(self.top_k, self.max_candidates)
        return self.top_k

    @property
    def checks_place_repetition(self) -> bool:
        """Whether ``Localizer.localize`` checks a localized global answer's place repetition: ``max_place_repetition``
        is set and the pose method is the guided estimate (the bar was chosen for it)."""
        return self.max_place_repetition is not None and self.pose_method == "guided"

    @property
    def effective_min_inlier_ratio(self) -> float:
        """``min_inlier_ratio``, or the pose method's default when it is None."""
        if self.min_inlier_ratio is not None:
            return self.min_inlier_ratio
        return default_confidence_model().min_aligned_ratio if self.pose_method == "guided" else 0.0

    def __post_init__(self) -> None:
        for f in fields(self):  # top_k=2.5 failed at localize time as a slice index
            value = getattr(self, f.name)
            if f.type in ("int", "int | None") and value is not None and (
                    isinstance(value, bool) or not isinstance(value, (int, np.integer))):
                raise ConfigError(f"{f.name} must be a whole number, got {value!r}")
        if self.top_k < 1 or self.verify_k < 1:
            raise ConfigError(f"top_k and verify_k must be >= 1, got {self.top_k} and {self.verify_k}")
        if self.expansion_block is not None and self.expansion_block < 1:
            raise ConfigError(f"expansion_block must be >= 1 or None, got {self.expansion_block}")
        if self.max_candidates < 1 or not 0.0 <= self.expand_below_screen_score <= 1.0:
            raise ConfigError("max_candidates must be >= 1 and expand_below_screen_score in [0, 1], got "
                              f"{self.max_candidates} and {self.expand_below_screen_score}")
        if self.min_inliers < 2:
            raise ConfigError(f"min_inliers must be >= 2 (a 2-D rigid fit needs two points), got {self.min_inliers}")
        if self.stop_verify_ratio is not None and not 0.0 <= self.stop_verify_ratio <= 1.0:
            raise ConfigError(f"stop_verify_ratio must be in [0, 1] or None, got {self.stop_verify_ratio}")
        if self.min_inlier_ratio is not None and not 0.0 <= self.min_inlier_ratio <= 1.0:
            raise ConfigError(f"min_inlier_ratio must be in [0, 1], got {self.min_inlier_ratio}")
        if self.pose_method not in ("guided", "mutual_nn"):
            raise ConfigError(f"pose_method must be 'guided' or 'mutual_nn', got {self.pose_method!r}")
        if self.min_confidence is not None and not 0.0 <= self.min_confidence <= 1.0:
            raise ConfigError(f"min_confidence must be in [0, 1], got {self.min_confidence}")
        if self.verify_ties < 0:
            raise ConfigError(f"verify_ties must be >= 0, got {self.verify_ties}")
        if self.prescreen_keep is not None and self.prescreen_keep < 1:
            raise ConfigError(f"prescreen_keep must be >= 1 or None, got {self.prescreen_keep}")
        if self.min_place_margin is not None and not 0.0 <= self.min_place_margin <= 1.0:
            raise ConfigError(f"min_place_margin must be in [0, 1] or None, got {self.min_place_margin}")
        if self.max_place_repetition is not None and not self.max_place_repetition > 0.0:
            raise ConfigError(f"max_place_repetition must be > 0 or None, got {self.max_place_repetition}")
        if self.repetition_rivals < 1 or self.repetition_neighbours < 1 or self.repetition_verify < 1:
            raise ConfigError("repetition_rivals, repetition_neighbours and repetition_verify must be >= 1, got "
                              f"{self.repetition_rivals}, {self.repetition_neighbours}, {self.repetition_verify}")
        if not self.place_margin_radius_m > 0.0:
            raise ConfigError(f"place_margin_radius_m must be > 0, got {self.place_margin_radius_m}")
        if self.prescreen_source_points < 2 or self.prescreen_hypotheses < 1:
            raise ConfigError("prescreen_source_points must be >= 2 and prescreen_hypotheses >= 1, got "
                              f"{self.prescreen_source_points} and {self.prescreen_hypotheses}")

    @property
    def effective_min_confidence(self) -> float:
        """``min_confidence``, or the shipped confidence model's bar when it is None."""
        if self.min_confidence is not None:
            return self.min_confidence
        return default_confidence_model().min_confidence


class _Prepared(Protocol):
    """What a candidate's ``loader`` returns (``keyframes.CachedKeyframe``): features + screen data."""

    features: ScanFeatures
    screen: ScreenKeyframe


@dataclass
class Candidate:
    """A retrieved map keyframe.

    Attributes:
        keyframe_id: index of the keyframe in its map.
        T_map_keyframe: (3,) float64 keyframe pose in the map frame (x m, y m, yaw rad).
        features: the keyframe's stored features (keypoints in its sensor frame, metres).
        descriptor_distance: Euclidean distance between unit global descriptors, in [0, 2].
        rank: 0-based position in the retrieval list.
        landmark_grid: ``build_landmark_grid(features.keypoints_xy_m)`` when the caller caches it per keyframe
            (else ``grid_loader`` or built on the fly).
        loader: instead of ``features`` (None): returns the keyframe's features and screen data
            (``keyframes.CachedKeyframe``) when the candidate is first needed, so retrieving many candidates
            costs nothing for those never screened.
        screen: the keyframe's ``ScreenKeyframe`` (built from ``features`` when neither it nor a loader is given).
        grid_loader: returns the keyframe's ``LandmarkGrid`` for the full pose estimate (e.g. from a cache).
    """

    keyframe_id: int
    T_map_keyframe: np.ndarray
    features: ScanFeatures | None
    descriptor_distance: float
    rank: int
    landmark_grid: LandmarkGrid | None = None
    loader: Callable[[], _Prepared] | None = None
    screen: ScreenKeyframe | None = None
    grid_loader: Callable[[], LandmarkGrid] | None = None

    def resolve(self) -> ScanFeatures:
        """The keyframe's features, loading them (and the screen data) through ``loader`` on first use."""
        if self.features is None:
            if self.loader is None:
                raise ConfigError(f"candidate keyframe {self.keyframe_id} has neither features nor a loader")
            prepared = self.loader()
            self.features, self.screen = prepared.features, self.screen or prepared.screen
        return self.features

    def screen_data(self, config: AlignmentConfig) -> ScreenKeyframe:
        """The keyframe's ``ScreenKeyframe`` (loaded, or built from its features)."""
        features = self.resolve()
        if self.screen is None:
            self.screen = screen_keyframe(features.keypoints_xy_m, features.local_descriptors, config)
        return self.screen

    def grid(self) -> LandmarkGrid | None:
        """The keyframe's ``LandmarkGrid`` when one is given or loadable, else None (built by the estimator)."""
        if self.landmark_grid is None and self.grid_loader is not None:
            self.landmark_grid = self.grid_loader()
        return self.landmark_grid


@dataclass
class CandidateVerification:
    """Geometric verification of one candidate.

    Attributes:
        T_keyframe_query: (3,) float64 relative pose (x m, y m, yaw rad) of the query in the keyframe's
            sensor frame, or None when RANSAC failed.
        num_matches: mutual nearest-neighbour descriptor matches; num_inliers: RANSAC inliers;
        inlier_ratio: inliers / matches (0 without matches).
        screen_score: ``guided`` only: fraction of query landmarks aligned by the cheap screen, in [0, 1]
            (None when not screened; the coarse prescreen's score for a candidate of an expansion round outside
            its best ``prescreen_keep``); candidates not among the best ``verify_k`` keep 0 inliers and reason
            ``screened_out``.
        ambiguity: ``guided`` only: the pose estimator's best rival pose's alignment score / the answer's
            (``RigidEstimate.ambiguity``; None where not computed).
        inlier_spread_m: spatial spread of the inlier query landmarks (``confidence.landmark_spread_m``,
            metres; None without a fit).
    """

    keyframe_id: int
    rank: int
    descriptor_distance: float
    timestamp_us: int
    T_map_keyframe: np.ndarray
    num_matches: int
    num_inliers: int
    inlier_ratio: float
    T_keyframe_query: np.ndarray | None
    reason: str | None = None
    screen_score: float | None = None
    ambiguity: float | None = None
    inlier_spread_m: float | None = None


@dataclass
class LocalizationResult:
    """Outcome of ``localize``.

    Attributes:
        status: ``localized`` or ``not_localized``.
        reason: why not localized (``no_candidate``, ``too_few_matches``, ``too_few_inliers``,
            ``ambiguous``: a rival pose aligns as many landmarks, ``low_confidence``: below the confidence bar),
            else None. A candidate's own reason may also be ``screened_out`` or, in tracking,
            ``inconsistent_with_prior``.
        best: the chosen candidate's verification (the best one tried even when not localized; None when
            there was no candidate).
        T_map_query: (3,) float64 absolute pose (x m, y m, yaw rad) when localized, else None.
        candidates: every screened candidate in retrieval order (not verified in full: reason ``screened_out``).
        timings_ms: stage timings (``screen_ms``, ``pose_ms`` or ``match_ms`` + ``ransac_ms``, ``verify_ms``
            = all of it; tracking: ``track_ms``), milliseconds.
        mode: ``global`` (retrieval + screen + verify) or ``tracking`` (registered from a pose prior).
        tracking_lost: a tracking attempt found no consistent pose and this is the global fallback's answer.
        confidence: probability in [0, 1] that the winner's pose is within the success thresholds (shipped
            ``ConfidenceModel``; 0 without a pose), also when not localized.
        cues: the confidence's inputs (None without a pose).
        pose_covariance: (3, 3) float64 covariance of ``T_map_query`` (x m, y m, yaw rad; map frame; m^2, m rad,
            rad^2) when localized and ``config.covariance`` is on (``Localizer``): how precise the pose is, calibrated
            on the training splits (``matching.uncertainty``). None otherwise, and when fewer than
            ``covariance.min_pairs`` landmarks pair at the final pose or the computation fails numerically.
        motion_compensated: the answered pose is the motion-compensated one (``Localizer``; False: the rigid
            registration's, because the compensation is off, the winning keyframe's motion on the map is unknown or
            the fit was discarded).
    """

    status: Status
    reason: str | None
    best: CandidateVerification | None
    T_map_query: np.ndarray | None
    candidates: list[CandidateVerification]
    timings_ms: dict[str, float] = field(default_factory=dict)
    confidence: float = 0.0
    cues: ConfidenceCues | None = None
    mode: Literal["global", "tracking"] = "global"
    tracking_lost: bool = False
    pose_covariance: np.ndarray | None = None
    motion_compensated: bool = False

    @property
    def localized(self) -> bool:
        return self.status == "localized"

    @property
    def alignment_score(self) -> float:
        """The winner's inlier ratio (``guided``: fraction of the query's landmarks aligned with the keyframe's,
        in [0, 1]; 0 without a winner): the floor of the decision. Not a calibrated probability - that is
        ``confidence``; ``localized`` means this score reached ``min_inlier_ratio`` with ``min_inliers`` and
        (``guided``) ``confidence`` reached ``min_confidence``."""
        return float(self.best.inlier_ratio) if self.best is not None else 0.0


def verify_candidate(query: ScanFeatures, candidate: Candidate, config: LocalizationConfig,
                     timings_ms: dict[str, float] | None = None) -> CandidateVerification:
    """Estimate ``T_keyframe_query`` for one candidate with ``config.pose_method``."""
    kf = candidate.resolve()
    base = dict(keyframe_id=candidate.keyframe_id, rank=candidate.rank,
                descriptor_distance=float(candidate.descriptor_distance), timestamp_us=int(kf.timestamp_us),
                T_map_keyframe=np.asarray(candidate.T_map_keyframe, np.float64))
    t0 = time.perf_counter()
    if config.pose_method == "guided":
        est = estimate_pose_guided(query.keypoints_xy_m, query.local_descriptors, kf.keypoints_xy_m,
                                   kf.local_descriptors, replace(config.alignment, min_inliers=config.min_inliers),
                                   grid=candidate.grid())
        num_matches = int(query.keypoints_xy_m.shape[0])
        fit_xy = query.keypoints_xy_m
        if timings_ms is not None:
            timings_ms["pose_ms"] = timings_ms.get("pose_ms", 0.0) + (time.perf_counter() - t0) * 1e3
    else:
        if query.keypoints_xy_m.shape[0] and kf.keypoints_xy_m.shape[0]:
            pairs = match_descriptors(query.local_descriptors, kf.local_descriptors, ratio=config.match_ratio)
        else:
            pairs = np.zeros((0, 2), dtype=np.int64)
        t1 = time.perf_counter()
        num_matches = int(pairs.shape[0])
        if timings_ms is not None:
            timings_ms["match_ms"] = timings_ms.get("match_ms", 0.0) + (t1 - t0) * 1e3
        if num_matches < max(2, config.min_inliers):
            return CandidateVerification(**base, num_matches=num_matches, num_inliers=0, inlier_ratio=0.0,
                                         T_keyframe_query=None, reason=REASON_TOO_FEW_MATCHES)
        src = query.keypoints_xy_m[pairs[:, 0]].astype(np.float64)
        dst = kf.keypoints_xy_m[pairs[:, 1]].astype(np.float64)
        est = estimate_rigid_2d(src, dst, replace(config.ransac, min_inliers=config.min_inliers))
        fit_xy = src
        if timings_ms is not None:
            timings_ms["ransac_ms"] = timings_ms.get("ransac_ms", 0.0) + (time.perf_counter() - t1) * 1e3
    # inliers are reported even for a failed fit (diagnostics); only a successful fit yields a pose
    n_in = int(est.num_inliers)
    inlier_xy = fit_xy[np.asarray(est.inlier_mask, bool)]  # the query landmarks the pose rests on
    return CandidateVerification(
        **base,
        num_matches=num_matches,
        num_inliers=n_in,
        inlier_ratio=float(n_in / num_matches) if num_matches else 0.0,
        T_keyframe_query=np.asarray(est.pose, np.float64) if est.success else None,
        reason=None if est.success else (est.reason or REASON_TOO_FEW_INLIERS),
        ambiguity=float(est.ambiguity) if config.pose_method == "guided" else None,
        inlier_spread_m=landmark_spread_m(inlier_xy) if est.success else None,
    )


def _screened_out(candidate: Candidate) -> CandidateVerification:
    return CandidateVerification(keyframe_id=candidate.keyframe_id, rank=candidate.rank,
                                 descriptor_distance=float(candidate.descriptor_distance),
                                 timestamp_us=int(candidate.resolve().timestamp_us),
                                 T_map_keyframe=np.asarray(candidate.T_map_keyframe, np.float64), num_matches=0,
                                 num_inliers=0, inlier_ratio=0.0, T_keyframe_query=None, reason=REASON_SCREENED_OUT)


def localize(query: ScanFeatures, candidates: list[Candidate],
             config: LocalizationConfig | None = None) -> LocalizationResult:
    """Verify retrieved candidates and return the query's map pose (see module docstring).

    Args:
        query: the query scan's features.
        candidates: retrieved keyframes (``rank`` 0 = best); the first ``top_k`` are screened, more up to
            ``max_candidates`` only when none of those aligns well or the answer is refused (see
            ``LocalizationConfig``: ``expand_below_screen_score``, ``expand_on_refusal``).
        config: settings; default ``LocalizationConfig()``.
    """
    config = config or LocalizationConfig()
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    pool = sorted(candidates, key=lambda c: c.rank)
    ordered = pool[: config.top_k] if config.rerank else pool[:1]
    scores: dict[int, float] = {}

    def screen(batch: list[Candidate], alignment: AlignmentConfig = config.alignment) -> None:
        # all candidates of a block at once (``screening``)
        values = screen_candidates(query.keypoints_xy_m, query.local_descriptors,
                                   [c.screen_data(config.alignment) for c in batch], alignment)
        scores.update({c.rank: float(v) for c, v in zip(batch, values, strict=True)})

    guided = config.pose_method == "guided"
    limit = min(len(pool), config.num_to_retrieve)

    def screen_next(block: int) -> None:  # the next ``block`` retrieved candidates join the screened ones
        t1 = time.perf_counter()
        batch = pool[len(ordered): min(limit, len(ordered) + block)]
        keep = config.prescreen_keep
        if keep is not None and len(batch) > keep:
            # coarse scores for the whole round, then the full screen of its best ``keep`` (``prescreen_keep``)
            screen(batch, config.prescreen_alignment)
            screen(sorted(batch, key=lambda c: (-scores[c.rank], c.rank))[:keep])
        else:
            screen(batch)
        ordered.extend(batch)
        timings["screen_ms"] = timings.get("screen_ms", 0.0) + (time.perf_counter() - t1) * 1e3

    if guided and len(ordered) > config.verify_k:
        screen(ordered)
        timings["screen_ms"] = (time.perf_counter() - t0) * 1e3
        while max(scores.values()) < config.expand_below_screen_score and len(ordered) < limit:
            screen_next(config.expansion_block or limit)
    done: dict[int, CandidateVerification] = {}
    while True:
        result = _verify_and_decide(query, ordered, scores, done, config, timings, t0)
        # refused: screen the next block and verify the best new ones (``expand_on_refusal``)
        if (result.localized or not guided or not config.expand_on_refusal or len(ordered) >= limit
                or len(ordered) <= config.verify_k):
            return result
        screen_next(config.expansion_block or limit)


def _verify_and_decide(query: ScanFeatures, ordered: list[Candidate], scores: dict[int, float],
                       done: dict[int, CandidateVerification], config: LocalizationConfig,
                       timings: dict[str, float], t0: float) -> LocalizationResult:
    """Verify the best-screened candidates not verified yet (into ``done``) and decide over all of ``done``."""
    ties: list[Candidate] = []  # screened as well as the best, checked after it (``verify_ties``)
    if scores:
        fresh = [c for c in sorted(ordered, key=lambda c: (-scores[c.rank], c.rank)) if c.rank not in done]
        keep = [c.rank for c in fresh[: config.verify_k]]
        if config.verify_ties > 0 and config.min_place_margin is not None:
            top = max(scores.values())
            ties = [c for c in fresh[config.verify_k:]
                    if scores[c.rank] >= top - config.min_place_margin][: config.verify_ties]
    else:
        keep = [c.rank for c in ordered]
    by_rank = {c.rank: c for c in ordered}
    for r in keep:  # best screened first; stop once one answer is confident enough (``stop_verify_ratio``)
        done[r] = v = verify_candidate(query, by_rank[r], config, timings)
        if (config.stop_verify_ratio is not None and v.T_keyframe_query is not None
                and v.num_inliers >= config.min_inliers and v.inlier_ratio >= config.stop_verify_ratio):
            ties = []
            break
    if ties:
        _verify_inconsistent_ties(query, ties, scores, done, config, timings)
    verified = [done[c.rank] if c.rank in done else _screened_out(c) for c in ordered]
    for v in verified:
        v.screen_score = scores.get(v.rank)
    timings["verify_ms"] = (time.perf_counter() - t0) * 1e3
    if not verified:
        return LocalizationResult("not_localized", REASON_NO_CANDIDATE, None, None, [], timings)
    # most inliers wins; ties go to the better retrieval rank
    best = max(verified, key=lambda v: (v.num_inliers, -v.rank))
    ok = (
        best.T_keyframe_query is not None
        and best.num_inliers >= config.min_inliers
        and best.inlier_ratio >= config.effective_min_inlier_ratio
    )
    # confidence hook (reradar_core.localization.confidence): cues of the winner -> calibrated probability
    model = default_confidence_model()
    cues, confidence = answer_confidence(best, verified, model)
    if not ok:
        reason = _refusal_reason(best, config)
        return LocalizationResult("not_localized", reason, best, None, verified, timings, confidence, cues)
    if config.min_place_margin is not None and _place_margin(best, verified, config) < config.min_place_margin:
        # another place screens about as well: which one wins is chance (``min_place_margin``)
        return LocalizationResult("not_localized", REASON_AMBIGUOUS, best, None, verified, timings, confidence, cues)
    if config.pose_method == "guided" and confidence < config.effective_min_confidence:
        return LocalizationResult("not_localized", REASON_LOW_CONFIDENCE, best, None, verified, timings,
                                  confidence, cues)
    assert best.T_keyframe_query is not None
    T_map_query = compose(best.T_map_keyframe, best.T_keyframe_query)
    return LocalizationResult("localized", None, best, np.asarray(T_map_query, np.float64), verified, timings,
                              confidence, cues)


def _refusal_reason(best: CandidateVerification, config: LocalizationConfig) -> str:
    """Why the best candidate, which did not pass, is refused: ``too_few_matches`` when the estimator had too few,
    else ``too_few_inliers`` below the floor (``min_inliers``, the aligned share) whatever else the estimator saw,
    and its own ``ambiguous`` (two poses aligning alike) only for an answer at or above the floor. QA session 38:
    answers with 20-30 % of their landmarks aligned read "ambiguous", which suggests a repeated street rather than
    an unknown place."""
    below_floor = best.num_inliers < config.min_inliers or best.inlier_ratio < config.effective_min_inlier_ratio
    if best.reason == REASON_TOO_FEW_MATCHES or (best.reason == REASON_AMBIGUOUS and not below_floor):
        return best.reason
    return REASON_TOO_FEW_INLIERS


def _verify_inconsistent_ties(query: ScanFeatures, ties: list[Candidate], scores: dict[int, float],
                              done: dict[int, CandidateVerification], config: LocalizationConfig,
                              timings: dict[str, float]) -> None:
    """``verify_ties``: verify each candidate that screened as well as the best one (within ``min_place_margin``)
    when the answer verified so far, seen from that candidate's keyframe, aligns clearly fewer of the query's
    landmarks than the candidate's own screen did: its screen found another pose, as good, and which of the two
    the screen order put first is chance. An answer that agrees with the tie (the usual case: keyframes a few
    metres apart seeing one place) costs one alignment count per tie, not a verification."""
    verified = [v for v in done.values() if v.T_keyframe_query is not None]
    if not verified:
        return
    best = max(verified, key=lambda v: (v.num_inliers, -v.rank))
    assert best.T_keyframe_query is not None
    T_map_query = compose(best.T_map_keyframe, best.T_keyframe_query)
    n = int(query.keypoints_xy_m.shape[0])
    margin = config.margin_landmarks(n)
    for c in ties:
        grid = c.grid()
        if grid is None:
            grid = build_landmark_grid(c.resolve().keypoints_xy_m.astype(np.float64), config.alignment.grid_cell_m)
        T_kf_query = compose(inverse(np.asarray(c.T_map_keyframe, np.float64)), T_map_query)
        seen = int(count_aligned(T_kf_query, query.keypoints_xy_m, grid, config.alignment.score_threshold_m)[0])
        if seen < scores[c.rank] * n - margin:
            done[c.rank] = verify_candidate(query, c, config, timings)


def _place_margin(best: CandidateVerification, candidates: list[CandidateVerification],
                  config: LocalizationConfig) -> float:
    """The winner's screen score minus the best of the candidates whose keyframe lies farther than
    ``config.place_margin_radius_m`` from the answer's map position (1.0 when there is none): ``min_place_margin``."""
    if best.T_keyframe_query is None:
        return 1.0
    T_map_query = np.asarray(compose(best.T_map_keyframe, best.T_keyframe_query), np.float64)
    rivals = [candidate_score(c) for c in candidates if c.rank != best.rank and float(np.hypot(
        *(np.asarray(c.T_map_keyframe, np.float64)[:2] - T_map_query[:2]))) > config.place_margin_radius_m]
    return candidate_score(best) - max(rivals) if rivals else 1.0


def answer_confidence(best: CandidateVerification, candidates: list[CandidateVerification],
                      model: ConfidenceModel) -> tuple[ConfidenceCues | None, float]:
    """The winner's ``ConfidenceCues`` among ``candidates`` and ``model``'s probability (0.0 without cues)."""
    cues = confidence_cues(best, candidates, model.place_radius_m, model.top_n)
    return cues, (float(model.predict(cues)) if cues is not None else 0.0)
