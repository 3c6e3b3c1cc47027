"""ReRadar itself behind the baseline interface: learned global descriptor + landmark pose verification.

Retrieval: Euclidean distance between unit global descriptors (``DescriptorExtractor``); localization: the
top-k candidates go through ``reradar_core.localization.localize`` (landmark-alignment screen of the top 20, and
of up to 60 when none aligns well, full guided pose estimation of the best 3, re-ranking by inliers), which
gives the answer keyframe and ``T_map_query``.
Model names come from ``reradar_core.model.available_models()`` (e.g. ``default``, ``our-1``, ``our-3-...``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from reradar_core.baselines.base import (
    EuclideanIndex,
    PlaceRecognitionMethod,
    Prepared,
    Retrieval,
    landmarks_for,
)
from reradar_core.features import ScanFeatures
from reradar_core.geometry.se2 import relative_pose
from reradar_core.io.scan import RadarScan

__all__ = ["Ours", "load_extractor", "features_to_prepared", "prepared_to_features"]


def load_extractor(model: str = "default") -> Any:
    """The named model's ``DescriptorExtractor`` (``default`` = the shipped weights)."""
    from reradar_core.model import DescriptorExtractor

    if model in ("default", "", None):
        return DescriptorExtractor.from_pretrained()
    return DescriptorExtractor.from_pretrained(model)


def features_to_prepared(f: ScanFeatures) -> Prepared:
    return {"global": f.global_descriptor, "keypoints": f.keypoints_xy_m, "local": f.local_descriptors,
            "timestamp_us": np.asarray(f.timestamp_us, dtype=np.int64)}


def prepared_to_features(p: Prepared) -> ScanFeatures:
    return ScanFeatures(p["global"], p["keypoints"], p["local"], int(np.asarray(p["timestamp_us"])))


class Ours(PlaceRecognitionMethod):
    """ReRadar with the named model; full 3-DoF pose from landmark verification of the top-k candidates.

    Args:
        model: model name (``available_models()``) or an already-built extractor (tests inject fakes).
        localization: ``LocalizationConfig``; default the service's settings (top-5, re-ranking).
        name: method name in the results (default ``ours-<model>`` / ``ours``).
    """

    provides_pose = True
    provides_heading = True

    def __init__(self, model: str | Any = "default", localization: Any = None, name: str | None = None) -> None:
        from reradar_core.localization import LocalizationConfig

        self.extractor = load_extractor(model) if isinstance(model, str) else model
        self.model_name = model if isinstance(model, str) else str(getattr(model, "model_id", "custom"))
        self.name = name or ("ours" if self.model_name == "default" else f"ours-{self.model_name}")
        self.localization = localization or LocalizationConfig()
        self._keyframes: Any = None  # KeyframeCandidates of the current database (grids built once)
        self._keyframes_of: int | None = None

    def params(self) -> dict[str, Any]:
        return {"model": str(getattr(self.extractor, "model_id", self.model_name)),
                "sha": str(getattr(self.extractor, "weights_sha256", "")), "v": 1}

    def prepare(self, scan: RadarScan) -> Prepared:
        lm = landmarks_for(scan, getattr(self.extractor, "landmark_config", None))
        return features_to_prepared(self.extractor.describe(scan, landmarks=lm))

    def describe_prepared(self, prepared: Prepared) -> np.ndarray:
        return np.asarray(prepared["global"], dtype=np.float32)

    def build_index(self, db_descs: Any) -> Any:
        return EuclideanIndex(db_descs)

    def distance(self, q_desc: np.ndarray, index: Any) -> np.ndarray:
        return index.distances(q_desc)

    def localize(self, q_prepared: Prepared, q_desc: np.ndarray, index: Any,
                 db_prepared: Sequence[Prepared], db_poses: np.ndarray) -> Retrieval:
        from reradar_core.localization import KeyframeCandidates, localize

        if self._keyframes_of != id(db_prepared):  # as the service does: each keyframe's grid is built once
            self._keyframes = KeyframeCandidates(lambda j: prepared_to_features(db_prepared[j]),
                                                 self.localization.alignment.grid_cell_m)
            self._keyframes_of = id(db_prepared)
        d = self.distance(q_desc, index)
        order = np.argsort(d, kind="stable")[: self.localization.num_to_retrieve]
        cands = [self._keyframes.candidate(int(j), db_poses[j], float(d[j]), rank) for rank, j in enumerate(order)]
        res = localize(prepared_to_features(q_prepared), cands, self.localization)
        j = int(res.best.keyframe_id) if res.best is not None else int(order[0])
        if res.localized and res.T_map_query is not None:
            heading = float(relative_pose(db_poses[j], res.T_map_query)[2])
            return Retrieval(j, float(d[j]), heading, np.asarray(res.T_map_query, np.float64))
        return Retrieval(j, float(d[j]), None, None)
