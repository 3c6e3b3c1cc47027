"""ReRadar itself behind the baseline interface: learned global descriptor + landmark pose verification.

The same code path as the service: a ``reradar_core.localization.Localizer`` over the database (FAISS
``GlobalIndex`` on the unit global descriptors, keyframes in memory) retrieves, screens (landmark alignment of
the top 10, and of up to 60 when none aligns well or the answer is refused: that deeper round coarsely, its
best 5 in full) and verifies (full guided pose
estimation of the best ``verify_k``, 1 by default, re-ranking by inliers), which gives the answer keyframe and ``T_map_query``. ``distance`` (PR curves) is the
Euclidean distance between unit descriptors over the whole database.
Model names come from ``reradar_core.model.available_models()`` (e.g. ``default``, ``our-1``, ``our-3-...``).
With ``far_view`` (method names ending in ``+far``), a refused answer is localized again in the far view
(``reradar_core.localization.far_view``): every scan is described in both views up front (the benchmark does not time
it), and the answer names ``TwoViewResult.place_id``; ``distance`` stays the near view's; the descriptor-alone top 1
(``Retrieval.descriptor_index``) is ``two_view_top1``: the far descriptor's for a query whose near view is sparse.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from typing import Any

import numpy as np

from reradar_core.baselines.base import PlaceRecognitionMethod, Prepared, Retrieval, landmarks_for
from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.se2 import relative_pose
from reradar_core.io.scan import RadarScan

__all__ = ["Ours", "load_extractor", "features_to_prepared", "prepared_to_features", "two_view_top1"]


def load_extractor(model: str = "default") -> Any:
    """The named model's ``DescriptorExtractor`` (``default`` = the shipped weights)."""
    from reradar_core.model import DescriptorExtractor

    if model in ("default", "", None):
        return DescriptorExtractor.from_pretrained()
    return DescriptorExtractor.from_pretrained(model)


def features_to_prepared(f: ScanFeatures) -> Prepared:
    return {"global": f.global_descriptor, "keypoints": f.keypoints_xy_m, "local": f.local_descriptors,
            "timestamp_us": np.asarray(f.timestamp_us, dtype=np.int64)}


def _far_part(p: Prepared) -> Prepared:
    """The far view's features of a prepared scan (keys ``far_*``)."""
    return {k[len("far_"):]: v for k, v in p.items() if k.startswith("far_")}


def prepared_to_features(p: Prepared) -> ScanFeatures:
    return ScanFeatures(p["global"], p["keypoints"], p["local"], int(np.asarray(p["timestamp_us"])))


def two_view_top1(q_prepared: Prepared, near_index: Any, far_index: Any, far_view: Any) -> int:
    """The database index the two-view method's global descriptors name alone, before any screen
    (``localization.far_view.retrieval_view``: the far descriptor's nearest keyframe for a query whose near view is
    sparse, else the near descriptor's). ``q_prepared`` holds both views' features (``Ours.prepare`` with a far
    view); ``near_index`` / ``far_index``: the database's ``GlobalIndex`` of each view."""
    from reradar_core.localization.far_view import VIEW_FAR, retrieval_view

    if retrieval_view(prepared_to_features(q_prepared), far_view) == VIEW_FAR:
        index, g = far_index, q_prepared["far_global"]
    else:
        index, g = near_index, q_prepared["global"]
    return int(index.search(np.asarray(g, np.float32).reshape(-1), 1)[0][0, 0])


class Ours(PlaceRecognitionMethod):
    """ReRadar with the named model; full 3-DoF pose from landmark verification of the top-k candidates.

    Args:
        model: model name (``available_models()``) or an already-built extractor (tests inject fakes).
        localization: ``LocalizationConfig``; default the service's settings (``LocalizationConfig()``).
        name: method name in the results (default ``ours-<model>`` / ``ours``).
    """

    provides_pose = True
    provides_heading = True

    def __init__(self, model: str | Any = "default", localization: Any = None, name: str | None = None,
                 far_view: Any = None, dense: bool = False) -> None:
        from reradar_core.localization import LocalizationConfig

        self.extractor = load_extractor(model) if isinstance(model, str) else model
        # ReRadar's far view (``localization.far_view``): a second look at the whole range for refused queries
        self.far_view = far_view
        self.far_extractor = self.extractor.with_view(far_view.cartesian) if far_view is not None else None
        if far_view is not None and far_view.landmark_z_q is not None:
            from dataclasses import replace

            from reradar_core.landmarks import Cen2018Config

            base = getattr(self.extractor, "landmark_config", None) or Cen2018Config()
            self.far_extractor.landmark_config = replace(base, z_q=float(far_view.landmark_z_q))
        if dense and far_view is None:
            raise ConfigError("dense registration is a step of the far view: pass a far_view too")
        # the far view's dense registration (``matching.dense``) for queries both views refused
        self.dense = bool(dense)
        self._far_localizer: Any = None
        self.model_name = model if isinstance(model, str) else str(getattr(model, "model_id", "custom"))
        self.name = name or ("ours" if self.model_name == "default" else f"ours-{self.model_name}")
        self.localization = localization or LocalizationConfig()
        self._localizer: Any = None  # Localizer of the current database (keyframe grids built once)
        # the database it was built for: the index and scan list themselves (held, so that their ids cannot be
        # reused by other objects) and a digest of the keyframe poses (new poses for the same scans: a new map)
        self._localizer_of: tuple[Any, Any, str] | None = None

    def params(self) -> dict[str, Any]:
        out = {"model": str(getattr(self.extractor, "model_id", self.model_name)),
               "sha": str(getattr(self.extractor, "weights_sha256", "")), "v": 1}
        if self.far_view is not None:
            out["far_view"] = [int(self.far_view.width_px), float(self.far_view.resolution_m)]
            if self.far_view.landmark_z_q is not None:
                out["far_view"].append(float(self.far_view.landmark_z_q))
        if self.dense:
            out["dense"] = repr(self.far_view.dense)
        return out

    def prepare(self, scan: RadarScan) -> Prepared:
        # only the landmarks within the image's reach: the keypoints are the same, the detector looks less far
        lm = landmarks_for(scan, getattr(self.extractor, "landmark_config", None),
                           getattr(self.extractor, "landmark_range_m", None))
        prepared = features_to_prepared(self.extractor.describe(scan, landmarks=lm))
        if self.far_extractor is not None:
            # the bench describes every scan up front; the far view is used only for refused queries
            far_lm = landmarks_for(scan, getattr(self.far_extractor, "landmark_config", None),
                                   self.far_extractor.landmark_range_m)
            prepared.update({f"far_{k}": v for k, v in
                             features_to_prepared(self.far_extractor.describe(scan, landmarks=far_lm)).items()})
        if self.dense:  # the far view's dense image (``matching.dense.dense_image``), stored as a map would
            from reradar_core.matching.dense import dense_image

            prepared["dense"] = dense_image(scan, self.far_view.cartesian, self.far_view.dense).astype(np.float16)
        return prepared

    def describe_prepared(self, prepared: Prepared) -> np.ndarray:
        return np.asarray(prepared["global"], dtype=np.float32)

    def build_index(self, db_descs: Any) -> Any:
        from reradar_core.retrieval import GlobalIndex

        return GlobalIndex(np.stack([np.asarray(d, np.float32).reshape(-1) for d in db_descs]))

    def distance(self, q_desc: np.ndarray, index: Any) -> np.ndarray:
        return index.distances(q_desc)

    def localizer(self, index: Any, db_prepared: Sequence[Prepared], db_poses: np.ndarray) -> Any:
        """The ``Localizer`` over this database (built once per database, as the service keeps one per map),
        every keyframe's screen data read at construction, as the service preloads a map that fits its cache."""
        from reradar_core.localization import InMemoryKeyframes, Localizer

        poses_digest = hashlib.sha1(np.ascontiguousarray(db_poses, dtype=np.float64).tobytes()).hexdigest()
        built = self._localizer_of
        if built is None or built[0] is not index or built[1] is not db_prepared or built[2] != poses_digest:
            keyframes = InMemoryKeyframes(lambda j: prepared_to_features(db_prepared[j]), db_poses,
                                          np.array([int(np.asarray(p["timestamp_us"])) for p in db_prepared]))
            self._localizer = Localizer(index, keyframes, self.localization, preload=True)
            self._far_localizer = None
            if self.far_extractor is not None:
                from reradar_core.retrieval import GlobalIndex

                far = [_far_part(p) for p in db_prepared]
                far_index = GlobalIndex(np.stack([np.asarray(p["global"], np.float32).reshape(-1) for p in far]))
                far_keyframes = InMemoryKeyframes(lambda j: prepared_to_features(far[j]), db_poses,
                                                  keyframes.timestamps_us)
                self._far_localizer = Localizer(far_index, far_keyframes, self.localization, preload=True)
            self._localizer_of = (index, db_prepared, poses_digest)
        return self._localizer

    def ready_database(self, index: Any, db_prepared: Sequence[Prepared], db_poses: np.ndarray) -> None:
        """Build the database's ``Localizer`` and measure every keyframe's place repetition, as ``reradar build-map``
        stores it in a served map: map-building work, outside the queries' timing."""
        localizer = self.localizer(index, db_prepared, db_poses)
        if self.localization.checks_place_repetition:
            localizer.place_repetitions(self.localization)
            if self._far_localizer is not None:
                self._far_localizer.place_repetitions(self.localization)

    def localize(self, q_prepared: Prepared, q_desc: np.ndarray, index: Any,
                 db_prepared: Sequence[Prepared], db_poses: np.ndarray) -> Retrieval:
        from reradar_core.localization import localize_two_views

        localizer = self.localizer(index, db_prepared, db_poses)
        far = None if self._far_localizer is None else (lambda: prepared_to_features(_far_part(q_prepared)))
        dense_q = dense_kf = None
        if self.dense and self._far_localizer is not None:
            def dense_q() -> np.ndarray:
                return np.asarray(q_prepared["dense"], np.float32)

            def dense_kf(j: int) -> np.ndarray:
                return np.asarray(db_prepared[j]["dense"], np.float32)
        answer = localize_two_views(localizer, prepared_to_features(q_prepared), self._far_localizer, far,
                                    self.localization, self.far_view, dense_q, dense_kf)
        res = answer.result
        if res.best is None:  # nothing retrieved: the database is empty
            raise ConfigError("the database holds no scans: nothing to localize against")
        j = int(answer.place_id) if answer.place_id is not None else int(res.best.keyframe_id)
        # the score a PR curve thresholds stays the near view's (the far view's distances are on another scale:
        # its no-match queries lie nearer than the near view's true matches, so mixing them costs F1max points)
        near = answer.near_result
        dist = float((near.best or res.best).descriptor_distance)
        # the global descriptor's own top 1 (retrieval rank 0), before the landmark screen re-ranks: the near view's,
        # or with a far view the two-view reading (the far descriptor's for a sparse near view: ``two_view_top1``)
        if self._far_localizer is not None:
            top = two_view_top1(q_prepared, index, self._far_localizer.index, self.far_view)
        else:
            top = min(near.candidates, key=lambda c: c.rank).keyframe_id if near.candidates else j
        if res.localized and res.T_map_query is not None:
            heading = float(relative_pose(db_poses[j], res.T_map_query)[2])
            return Retrieval(j, dist, heading, np.asarray(res.T_map_query, np.float64), descriptor_index=int(top),
                             pose_covariance=res.pose_covariance)
        return Retrieval(j, dist, None, None, descriptor_index=int(top))
