"""The far view: a second look at the whole radar range when the paper's view has nothing to go on.

The paper's network sees a 201 px Cartesian image at 0.64 m/px (+-64 m, Sec. "Implementation Details"), while a
Navtech radar reaches 165 m. Where nothing persistent stands within 64 m of the road (open moor, a loch shore,
level farmland: simulator v11's open land on ``offroad-sim-hard``), the near view holds only transient ground
clutter: the answer is refused (or, worse, retrieved wrong), while the hand-made baselines, which read the whole
165 m, still find the place from what stands 80-165 m away.

``localize_two_views`` is ReRadar's own extension (not in the paper; benchmark rows carry ``+far``): the query is
localized in the near view as always; only when that answer is refused does the same network look again at a
coarse image of the whole range (``FarViewConfig``: 257 px at 1.28 m/px, +-164 m; no retraining: the network is
fully convolutional up to F' and NetVLAD aggregates any number of cells), and a second ``Localizer`` over the map's
far-view keyframe features (same keyframe ids) retrieves, screens, verifies and decides with the same code and
settings. Its answer replaces the refused one, localized or not (``TwoViewResult.place_id``: the place a refused
far answer names). Confident near answers never pay for the second look.

Dense registration (ours too; benchmark rows carry ``+dense``; docs/MODEL.md "Dense registration"): when the far view
refuses as well and the near view had little in view, and the caller can supply the far view's dense images
(``matching.dense.dense_image`` of the query and of the map's keyframes), the query is registered onto the far
answer's ``FarViewConfig.dense_candidates`` best-ranked candidates by whole-image correlation
(``matching.dense.register_dense_best``). The best alignment is ``localized`` only when its peak stands at least
``dense_min_heading_margin`` above every peak at another heading, its translation is unique
(``dense_min_shift_margin``, inside the search window) and its confidence (a logistic of the heading margin, fitted
on calibration routes) reaches the bar the landmark answers must reach; its pose then replaces the refused answer
(``TwoViewResult.registration`` = ``dense``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Literal

import numpy as np

from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.cartesian import CartesianConfig
from reradar_core.geometry.se2 import compose
from reradar_core.matching.dense import DenseConfig, register_dense_best

if TYPE_CHECKING:
    from reradar_core.localization.localizer import Localizer
    from reradar_core.localization.pipeline import LocalizationConfig, LocalizationResult

__all__ = ["FarViewConfig", "TwoViewResult", "localize_two_views", "far_fallback", "dense_fallback", "near_is_sparse",
           "retrieval_view", "VIEW_NEAR",
           "VIEW_FAR", "View", "Registration", "REGISTRATION_LANDMARKS", "REGISTRATION_DENSE"]

View = Literal["near", "far"]
VIEW_NEAR: View = "near"
VIEW_FAR: View = "far"
Registration = Literal["landmarks", "dense"]
REGISTRATION_LANDMARKS: Registration = "landmarks"
REGISTRATION_DENSE: Registration = "dense"


@dataclass(frozen=True)
class FarViewConfig:
    """Geometry of the far view's Cartesian image.

    Attributes:
        width_px: image width and height, px (default 257: odd, so the centre is a pixel and 90 degree rotations
            stay exact, as with the paper's 201; 257 x 1.28 / 2 = 164.5 m, the reach of the Navtech presets).
        resolution_m: metres per pixel (default 1.28, twice the paper's 0.64: the image costs 1.6x the near
            view's pixels instead of the 6.5x of 513 px at 0.64 m). On ``offroad-sim-hard`` (v11), descriptor
            alone with ``our-3-offroad-w05``: 257 px at 1.28 m retrieves 88 % of the revisit queries in open land
            against the near view's 33 %, but only 76 % of the others (near view: 100 %), so it is a fallback and
            not a replacement (docs/MODEL.md, "The far view").
        landmark_z_q: the far view's Cen 2018 detection threshold (``Cen2018Config.z_q``); None (default) = the
            near view's (paper: 3.0). 2.0 finds 5-10x the landmarks in open land but localized no more queries on
            a calibration route (docs/MODEL.md, "The far view"): a probe setting, not a default.
        sparse_landmarks: a near view holding fewer landmarks than this had little in view (default 512, the
            extractor's keypoint cap ``DEFAULT_MAX_KEYPOINTS``: a near view at the cap is full). Only then does a
            refused far answer name the far descriptor's top 1 (``TwoViewResult.place_id``); a full near view's
            refusal is about ambiguity, not emptiness, and its best-screened candidate stands.
        dense: ``matching.dense.DenseConfig``, the dense registration's image and search settings (used only when
            the caller supplies dense images: ``far_fallback``'s ``dense_query`` / ``dense_keyframe``).
        dense_candidates: how many of the refused far answer's best-ranked candidates are registered (default 5).
        dense_min_heading_margin: a dense answer is localized only when its coarse peak stands this much above the
            best peak at any other heading (``DenseRegistration.heading_margin``; default 0.05: twice the largest
            margin of a wrong dense pose, 0.025, on four calibration routes of the ``offroad-sim-hard``
            definition, world and route seeds 23-26 - 0 of 109 accepted answers wrong there, 109 of 135 right ones
            accepted; docs/MODEL.md "Dense registration").
        dense_min_shift_margin: ... and only when its translation is unique: the best peak at the answer's
            heading farther than ``dense.rival_shift_m`` (6 m) from it is at most 1 - this of the answer's
            (``DenseRegistration.shift_margin``; default 0.25: the right answers on the calibration routes have 0.53
            or more, scenes that align one step along themselves - synthetic straight banks and rows of posts in open
            land, where the heading margin passed wrong poses 10-52 m off (QA, session 39) - 0.08 or less); a peak
            on the border of the +-``dense.max_shift_m`` window (``at_edge``) is refused too.
        dense_confidence: (a, b) of the dense answer's confidence, 1 / (1 + exp(-(a + b ln margin))): the
            probability that the pose is within the success thresholds (25 m, 10 degrees), fitted by logistic
            regression on the same calibration routes' 187 sparse refused queries (predicted / observed per margin
            bin: 0.11 / 0.09 below 0.01, 0.47 / 0.50 to 0.02, 0.86 / 0.87 to 0.05, 0.98 / 1.00 to 0.1, 1.00 / 1.00
            above); 0.95 at the default margin bar.
        dense_pose_sigma: (along m, across m, yaw rad) standard deviations of a dense answer's pose error in the
            vehicle's frame (x along its heading, y across), its ``pose_covariance`` when the localization config's
            covariance is on. Default (0.42, 0.42, 0.007): the 109 dense answers on the same calibration routes
            (mid-sweep ground truth) have a position RMS of 0.42 m per axis and 0.40 deg in heading. Isotropic because
            the along / across split differs from route to route (across 0.7-3.3x along on three routes, 0.7x on the
            fourth); a first, anisotropic fit (0.24 / 0.54 m) was over-confident on ``offroad-sim-hard``'s drive,
            where along-track errors dominate (NEES 8.6): that drive was seen before this choice (docs/MODEL.md
            "Dense registration"). One covariance for every dense answer: the correlation peak's own shape is not
            calibrated.
    """

    width_px: int = 257
    resolution_m: float = 1.28
    landmark_z_q: float | None = None
    sparse_landmarks: int = 512
    dense: DenseConfig = DenseConfig()
    dense_candidates: int = 5
    dense_min_heading_margin: float = 0.05
    dense_min_shift_margin: float = 0.25
    dense_confidence: tuple[float, float] = (9.8817, 2.3069)
    dense_pose_sigma: tuple[float, float, float] = (0.42, 0.42, 0.007)

    def __post_init__(self) -> None:
        if isinstance(self.dense_candidates, bool) or not isinstance(self.dense_candidates, int) \
                or self.dense_candidates < 1:
            raise ConfigError(f"far view dense_candidates must be a whole number >= 1, got {self.dense_candidates!r}")
        if not (math.isfinite(self.dense_min_heading_margin) and self.dense_min_heading_margin > 0):
            raise ConfigError("far view dense_min_heading_margin must be a positive number, got "
                              f"{self.dense_min_heading_margin!r}")
        if not (math.isfinite(self.dense_min_shift_margin) and 0 <= self.dense_min_shift_margin < 1):
            raise ConfigError("far view dense_min_shift_margin must be in [0, 1), got "
                              f"{self.dense_min_shift_margin!r}")
        if len(self.dense_pose_sigma) != 3 or not all(math.isfinite(v) and v > 0 for v in self.dense_pose_sigma):
            raise ConfigError(f"far view dense_pose_sigma must be three positive numbers, got {self.dense_pose_sigma!r}")
        if len(self.dense_confidence) != 2 or not all(math.isfinite(v) for v in self.dense_confidence) \
                or self.dense_confidence[1] <= 0:
            raise ConfigError(f"far view dense_confidence must be (a, b) with b > 0, got {self.dense_confidence!r}")
        if self.sparse_landmarks < 0:
            raise ConfigError(f"far view sparse_landmarks must be >= 0, got {self.sparse_landmarks}")
        if self.landmark_z_q is not None and not self.landmark_z_q > 0:
            raise ConfigError(f"far view landmark threshold z_q must be positive, got {self.landmark_z_q}")
        if self.width_px < 3 or self.width_px % 2 != 1:
            raise ConfigError(f"far view width must be an odd number of pixels >= 3, got {self.width_px}")
        if not self.resolution_m > 0:
            raise ConfigError(f"far view resolution must be positive metres per pixel, got {self.resolution_m}")

    @property
    def cartesian(self) -> CartesianConfig:
        return CartesianConfig(self.width_px, self.resolution_m)

    @property
    def reach_m(self) -> float:
        """Half the image width, metres."""
        return self.width_px * self.resolution_m / 2.0

    def dense_pose_covariance(self, T_map_query: np.ndarray) -> np.ndarray:
        """(3, 3) covariance of a dense answer at ``T_map_query`` in the map frame (x m, y m, yaw rad):
        ``dense_pose_sigma`` along and across the vehicle's heading, rotated into the map."""
        along, across, yaw = self.dense_pose_sigma
        c, s = math.cos(float(T_map_query[2])), math.sin(float(T_map_query[2]))
        R = np.array([[c, -s], [s, c]])
        cov = np.zeros((3, 3))
        xy = R @ np.diag([along ** 2, across ** 2]) @ R.T
        cov[:2, :2] = 0.5 * (xy + xy.T)  # exactly symmetric, as the landmark answers' (rounding left 1e-18 apart, QA s41)
        cov[2, 2] = yaw ** 2
        return cov

    def dense_answer_confidence(self, heading_margin: float) -> float:
        """The calibrated confidence of a dense answer with this heading margin (``dense_confidence``), in [0, 1]."""
        a, b = self.dense_confidence
        z = a + b * math.log(max(float(heading_margin), 1e-6))
        return 1.0 / (1.0 + math.exp(-z)) if z > -700 else 0.0


@dataclass(frozen=True)
class TwoViewResult:
    """The answer and the view that gave it.

    Attributes:
        result: the ``LocalizationResult`` returned (the near view's, or the far view's when the near one was
            refused and a far view was available).
        view: ``VIEW_NEAR`` or ``VIEW_FAR``.
        near_result: the near view's own result (the same object as ``result`` when ``view`` is near).
        near_sparse: the near view held fewer landmarks than ``FarViewConfig.sparse_landmarks``.
        registration: how ``result``'s pose was found: ``landmarks`` (the paper's verification, either view) or
            ``dense`` (``dense_fallback``: whole-image correlation in the far view).
        heading_margin: the dense registration's ``DenseRegistration.heading_margin`` when one was tried, else
            None.
    """

    result: LocalizationResult
    view: View
    near_result: LocalizationResult
    near_sparse: bool = False
    registration: Registration = REGISTRATION_LANDMARKS
    heading_margin: float | None = None

    @property
    def place_id(self) -> int | None:
        """The map keyframe the answer names (place recognition, Recall@1).

        The winner when localized. When both views refused: if the near view had little in view (``near_sparse``:
        fewer landmarks than ``FarViewConfig.sparse_landmarks``), the far view's global-descriptor top 1 - such a
        scan holds 3-20 landmarks over the whole range in open land, too few to rank candidates by alignment,
        while the far descriptor still reads the place; otherwise the near view's best-screened candidate, as
        without a far view (docs/MODEL.md, "The far view": chosen on calibration routes, not on a benchmark
        drive). None when nothing was retrieved (an empty map).
        """
        r = self.result
        if r.best is None:
            return None
        if r.localized or self.view != VIEW_FAR:
            return int(r.best.keyframe_id)
        if self.near_sparse and r.candidates:
            return int(min(r.candidates, key=lambda c: c.rank).keyframe_id)
        near = self.near_result.best
        return int(near.keyframe_id) if near is not None else int(r.best.keyframe_id)


def near_is_sparse(near_features: ScanFeatures, far_view: FarViewConfig | None = None) -> bool:
    """The near view had little in view: it holds fewer landmarks than ``far_view.sparse_landmarks`` (default
    ``FarViewConfig()``)."""
    return len(near_features.keypoints_xy_m) < (far_view or FarViewConfig()).sparse_landmarks


def retrieval_view(near_features: ScanFeatures, far_view: FarViewConfig | None = None) -> View:
    """The view whose global descriptor names the two-view method's place before any screen: the far view for a
    query whose near view is sparse (``near_is_sparse``), else the near view - the reading ``TwoViewResult.place_id``
    gives a refused answer, applied to the descriptors alone (the two-view method's "descriptor alone" figure,
    ``baselines.ours.two_view_top1``; docs/MODEL.md "The two-view descriptor")."""
    return VIEW_FAR if near_is_sparse(near_features, far_view) else VIEW_NEAR


def localize_two_views(near: Localizer, near_features: ScanFeatures, far: Localizer | None,
                       far_features: Callable[[], ScanFeatures] | None,
                       config: LocalizationConfig | None = None,
                       far_view: FarViewConfig | None = None,
                       dense_query: Callable[[], np.ndarray] | None = None,
                       dense_keyframe: Callable[[int], np.ndarray] | None = None) -> TwoViewResult:
    """Localize in the near view; when refused, again in the far view (module docstring).

    Args:
        near: the map's ``Localizer`` over its near-view (model) keyframe features.
        near_features: the query's near-view ``ScanFeatures``.
        far: the map's ``Localizer`` over the same keyframes' far-view features, or None (no far view: the near
            answer stands).
        far_features: computes the query's far-view ``ScanFeatures`` (called only when needed), or None.
        config: ``LocalizationConfig`` for both views (None: each localizer's own).
        far_view: the far view's settings (None: ``FarViewConfig()``); its geometry is the caller's (the far
            features and dense images are made with it), ``sparse_landmarks`` and the ``dense_*`` settings are
            read here.
        dense_query: computes the query's far-view ``matching.dense.dense_image`` (called only when needed), or
            None: no dense registration.
        dense_keyframe: a map keyframe's far-view dense image by keyframe id, or None: no dense registration.
    """
    return far_fallback(near.localize(near_features, config), near, near_features, far, far_features, config,
                        far_view, dense_query, dense_keyframe)


def far_fallback(result: LocalizationResult, near: Localizer, near_features: ScanFeatures, far: Localizer | None,
                 far_features: Callable[[], ScanFeatures] | None, config: LocalizationConfig | None = None,
                 far_view: FarViewConfig | None = None,
                 dense_query: Callable[[], np.ndarray] | None = None,
                 dense_keyframe: Callable[[int], np.ndarray] | None = None) -> TwoViewResult:
    """The second half of ``localize_two_views``: ``result`` (the near view's global answer for ``near_features``,
    e.g. a tracked request's global fallback) stands when localized or without a far view; else the far view
    localizes the query (arguments as ``localize_two_views``).

    The far answer carries what the request went through before it: ``tracking_lost`` of ``result`` (a tracked
    request whose registration failed stays marked so, whichever view answers its global fallback) and the near
    attempt's stage timings, added to the far view's stage by stage (``timings_ms``: ``screen_ms`` is the time both
    views spent screening, ...; ``track_ms`` the tracking attempt), so the stages account for the whole request.
    """
    if result.localized or far is None or far_features is None:
        return TwoViewResult(result, VIEW_NEAR, result)
    if len(far) != len(near):
        raise ConfigError(f"the far view holds {len(far)} keyframes but the near view {len(near)}: "
                          "they must be the same map")
    far_view = far_view or FarViewConfig()
    sparse = near_is_sparse(near_features, far_view)
    answer = far.localize(far_features(), config)
    answer.tracking_lost = result.tracking_lost
    answer.timings_ms = {k: result.timings_ms.get(k, 0.0) + answer.timings_ms.get(k, 0.0)
                         for k in {**result.timings_ms, **answer.timings_ms}}
    if answer.localized or not sparse or dense_query is None or dense_keyframe is None or not answer.candidates:
        return TwoViewResult(answer, VIEW_FAR, result, near_sparse=sparse)
    settings = config or far.config
    dense, margin = dense_fallback(answer, dense_query, dense_keyframe, far_view, settings.effective_min_confidence,
                                   settings.covariance.enabled)
    return TwoViewResult(dense, VIEW_FAR, result, near_sparse=sparse,
                         registration=REGISTRATION_DENSE if dense.localized else REGISTRATION_LANDMARKS,
                         heading_margin=margin)


def dense_fallback(answer: LocalizationResult, dense_query: Callable[[], np.ndarray],
                   dense_keyframe: Callable[[int], np.ndarray], far_view: FarViewConfig,
                   min_confidence: float, covariance: bool = True) -> tuple[LocalizationResult, float]:
    """Register the query onto the refused far answer's best-ranked candidates by dense correlation (module
    docstring) and return (a ``localized`` answer when the best alignment passes both bars, else ``answer``
    itself with ``timings_ms["dense_ms"]`` added; the best alignment's heading margin).

    The localized answer: ``best`` is the winning candidate with ``T_keyframe_query`` from the registration (0
    matches and inliers: no landmarks were paired), ``T_map_query`` = ``T_map_keyframe`` o ``T_keyframe_query``,
    ``confidence`` = ``far_view.dense_answer_confidence(margin)``, no ``cues``, ``pose_covariance``
    ``far_view.dense_pose_covariance`` when ``covariance`` (the localization config's is on), ``candidates`` the far
    answer's with the winner's entry replaced by
    ``best``, ``tracking_lost`` the far answer's. ``timings_ms["dense_ms"]`` is the registration's time, after
    ``dense_query`` made the query's image (the caller times that).
    """
    from reradar_core.localization.pipeline import LocalizationResult

    query = dense_query()  # its own stage (the service times it as ``dense_image_ms``), not part of ``dense_ms``
    t0 = time.perf_counter()
    ranked = sorted(answer.candidates, key=lambda c: c.rank)[:far_view.dense_candidates]
    win, reg = register_dense_best(query, [dense_keyframe(int(c.keyframe_id)) for c in ranked],
                                   far_view.cartesian, far_view.dense)
    timings = {**answer.timings_ms, "dense_ms": 1e3 * (time.perf_counter() - t0)}
    confidence = far_view.dense_answer_confidence(reg.heading_margin)
    if (reg.heading_margin < far_view.dense_min_heading_margin or confidence < min_confidence
            or reg.shift_margin < far_view.dense_min_shift_margin or reg.at_edge):
        answer.timings_ms = timings
        return answer, reg.heading_margin
    chosen = ranked[win]
    T_map_keyframe = np.asarray(chosen.T_map_keyframe, np.float64)
    best = replace(chosen, num_matches=0, num_inliers=0, inlier_ratio=0.0,
                   T_keyframe_query=np.asarray(reg.T_keyframe_query, np.float64), reason=None, ambiguity=None,
                   inlier_spread_m=None)
    # the winner's entry in the candidate list is the dense answer (not the far view's screened-out refusal)
    candidates = [best if c is chosen else c for c in answer.candidates]
    T_map_query = compose(T_map_keyframe, reg.T_keyframe_query)
    return LocalizationResult("localized", None, best, T_map_query, candidates, timings, confidence, None,
                              mode=answer.mode, tracking_lost=answer.tracking_lost,
                              pose_covariance=far_view.dense_pose_covariance(T_map_query) if covariance else None
                              ), reg.heading_margin
