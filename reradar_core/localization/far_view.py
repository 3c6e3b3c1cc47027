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
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.cartesian import CartesianConfig

if TYPE_CHECKING:
    from reradar_core.localization.localizer import Localizer
    from reradar_core.localization.pipeline import LocalizationConfig, LocalizationResult

__all__ = ["FarViewConfig", "TwoViewResult", "localize_two_views", "far_fallback", "VIEW_NEAR", "VIEW_FAR", "View"]

View = Literal["near", "far"]
VIEW_NEAR: View = "near"
VIEW_FAR: View = "far"


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
    """

    width_px: int = 257
    resolution_m: float = 1.28
    landmark_z_q: float | None = None
    sparse_landmarks: int = 512

    def __post_init__(self) -> None:
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


@dataclass(frozen=True)
class TwoViewResult:
    """The answer and the view that gave it.

    Attributes:
        result: the ``LocalizationResult`` returned (the near view's, or the far view's when the near one was
            refused and a far view was available).
        view: ``VIEW_NEAR`` or ``VIEW_FAR``.
        near_result: the near view's own result (the same object as ``result`` when ``view`` is near).
    """

    result: LocalizationResult
    view: View
    near_result: LocalizationResult
    near_sparse: bool = False

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


def localize_two_views(near: Localizer, near_features: ScanFeatures, far: Localizer | None,
                       far_features: Callable[[], ScanFeatures] | None,
                       config: LocalizationConfig | None = None,
                       far_view: FarViewConfig | None = None) -> TwoViewResult:
    """Localize in the near view; when refused, again in the far view (module docstring).

    Args:
        near: the map's ``Localizer`` over its near-view (model) keyframe features.
        near_features: the query's near-view ``ScanFeatures``.
        far: the map's ``Localizer`` over the same keyframes' far-view features, or None (no far view: the near
            answer stands).
        far_features: computes the query's far-view ``ScanFeatures`` (called only when needed), or None.
        config: ``LocalizationConfig`` for both views (None: each localizer's own).
        far_view: the far view's settings (None: ``FarViewConfig()``); only ``sparse_landmarks`` is read here.
    """
    return far_fallback(near.localize(near_features, config), near, near_features, far, far_features, config,
                        far_view)


def far_fallback(result: LocalizationResult, near: Localizer, near_features: ScanFeatures, far: Localizer | None,
                 far_features: Callable[[], ScanFeatures] | None, config: LocalizationConfig | None = None,
                 far_view: FarViewConfig | None = None) -> TwoViewResult:
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
    sparse = len(near_features.keypoints_xy_m) < (far_view or FarViewConfig()).sparse_landmarks
    answer = far.localize(far_features(), config)
    answer.tracking_lost = result.tracking_lost
    answer.timings_ms = {k: result.timings_ms.get(k, 0.0) + answer.timings_ms.get(k, 0.0)
                         for k in {**result.timings_ms, **answer.timings_ms}}
    return TwoViewResult(answer, VIEW_FAR, result, near_sparse=sparse)
