"""The interface every place-recognition method implements, so the benchmark treats them all the same.

A method turns a scan into a *prepared* record (a dict of numpy arrays that depends only on the scan and the
method's fixed parameters, so the benchmark can cache it on disk), learns whatever it needs from the
reference (database) run in ``fit`` (VLAD vocabularies, NetVLAD centres; a no-op for most), turns prepared
records into global descriptors, and ranks a database by ``distance`` (lower = more similar).

Methods that also estimate the query's heading relative to the retrieved keyframe (ReFeree, RaPlace) override
``estimate_heading``; ours overrides ``localize`` to return a full 3-DoF pose.
"""

from __future__ import annotations

import hashlib
import json
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from reradar_core.io.scan import RadarScan, require_scan
from reradar_core.retrieval.index import EuclideanIndex  # the retrieval stage's exact search, re-exported

__all__ = ["Prepared", "PlaceRecognitionMethod", "Retrieval", "params_hash"]

#: Scan-dependent, database-independent intermediate record: what the feature cache stores.
Prepared = dict[str, np.ndarray]


def params_hash(params: dict[str, Any], length: int = 10) -> str:
    """Short stable hash of a JSON-serialisable parameter dict (cache keys)."""
    blob = json.dumps(params, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:length]


@dataclass
class Retrieval:
    """Answer of one method for one query.

    Attributes:
        index: database index of the best candidate (after any re-ranking).
        distance: descriptor distance of that candidate (lower = more confident; drives PR curves / F1max).
        heading_rad: estimated yaw of the query relative to the candidate (yaw of ``T_candidate_query``),
            radians counter-clockwise, or None when the method gives no heading.
        pose: estimated map-frame pose ``T_map_query`` (x [m], y [m], yaw [rad]), or None.
        descriptor_index: database index of the nearest global descriptor alone, before any re-ranking, for
            methods that re-rank (ReRadar's screen); None when ``index`` already is that (no re-ranking).
        pose_covariance: (3, 3) covariance of ``pose`` (x m, y m, yaw rad; map frame), or None (ReRadar's
            ``LocalizationResult.pose_covariance``; no other method gives one).
    """

    index: int
    distance: float
    heading_rad: float | None = None
    pose: np.ndarray | None = None
    descriptor_index: int | None = None
    pose_covariance: np.ndarray | None = None


class PlaceRecognitionMethod(ABC):
    """Base class: ``prepare`` -> ``fit`` (database) -> ``describe_prepared`` -> ``build_index`` / ``distance``.

    Subclasses set ``name`` and implement ``prepare``, ``describe_prepared`` and ``distance``.
    ``provides_heading`` / ``provides_pose`` tell the benchmark which success rule applies (paper,
    Sec. Evaluation Metrics): full pose -> translation and rotation errors; heading only -> correct retrieval
    and rotation error below 10 degrees; neither -> SR not applicable.
    """

    name: str = "method"
    provides_heading: bool = False
    provides_pose: bool = False
    #: True when ``fit`` uses the database (descriptors then depend on the reference run).
    needs_fit: bool = False
    #: Bump whenever ``prepare`` changes what it computes: part of the feature-cache key, so records made by
    #: an earlier algorithm are never reused.
    algorithm_version: int = 1

    # ------------------------------------------------------------------ identity
    def min_database_scans(self) -> int:
        """Fewest database scans ``fit`` can work with (1: any database; a method whose fit needs more says so)."""
        return 1

    def params(self) -> dict[str, Any]:
        """The parameters that change the prepared records (part of the cache key)."""
        return {}

    @property
    def cache_key(self) -> str:
        """Folder-safe key of this method + parameters + ``algorithm_version`` for the feature cache."""
        return f"{self.name}-{params_hash(self.params())}-a{self.algorithm_version}"

    # ------------------------------------------------------------------ pipeline
    @abstractmethod
    def prepare(self, scan: RadarScan) -> Prepared:
        """Scan -> database-independent record (cached by the benchmark)."""

    def fit(self, database: Sequence[Prepared]) -> None:  # noqa: B027 - optional hook, no-op by default
        """Learn from the reference run's prepared records (vocabulary, centres). No-op by default."""

    @abstractmethod
    def describe_prepared(self, prepared: Prepared) -> np.ndarray:
        """Prepared record -> global descriptor (any shape; compared only by this method's ``distance``)."""

    def describe(self, scan: RadarScan) -> np.ndarray:
        """Scan -> global descriptor (``prepare`` then ``describe_prepared``)."""
        return self.describe_prepared(self.prepare(require_scan(scan, f"{type(self).__name__}.describe")))

    def build_index(self, db_descs: Sequence[np.ndarray]) -> Any:
        """Database descriptors -> whatever ``distance`` searches (default: a stacked array)."""
        return np.stack([np.asarray(d) for d in db_descs])

    def ready_database(self, index: Any, db_prepared: Sequence[Prepared],  # noqa: B027 - optional hook
                       db_poses: np.ndarray) -> None:
        """Build whatever ``localize`` keeps per database beyond ``build_index`` (no-op by default). The
        benchmark calls it after ``build_index`` and outside the timed queries, as the service loads a map
        before it answers: per-query times then hold no one-off database work for any method."""

    @abstractmethod
    def distance(self, q_desc: np.ndarray, index: Any) -> np.ndarray:
        """(N,) float64 distances from one query descriptor to every database entry (lower = closer)."""

    def estimate_heading(self, q_desc: np.ndarray, index: Any, j: int) -> float | None:
        """Yaw [rad, CCW] of the query relative to database entry ``j``, or None if not supported."""
        return None

    def localize(self, q_prepared: Prepared, q_desc: np.ndarray, index: Any,
                 db_prepared: Sequence[Prepared], db_poses: np.ndarray) -> Retrieval:
        """Top-1 retrieval (+ heading where available). Ours overrides this with pose verification.

        Args:
            q_prepared: the query's prepared record.
            q_desc: the query's global descriptor.
            index: ``build_index`` of the database descriptors.
            db_prepared: the database's prepared records (for methods that verify geometrically).
            db_poses: (N, 3) map-frame database poses ``T_map_keyframe``.
        """
        d = self.distance(q_desc, index)
        j = int(np.argmin(d))
        return Retrieval(j, float(d[j]), self.estimate_heading(q_desc, index, j), None)


def polar_resize(power: np.ndarray, num_azimuths: int, num_range: int) -> np.ndarray:
    """Resize an (A, R) polar image to (num_azimuths, num_range) float32 with area averaging."""
    import cv2

    p = np.ascontiguousarray(power, dtype=np.float32)
    interp = cv2.INTER_AREA if (num_range <= p.shape[1] and num_azimuths <= p.shape[0]) else cv2.INTER_LINEAR
    return cv2.resize(p, (num_range, num_azimuths), interpolation=interp)


__all__ += ["polar_resize", "EuclideanIndex"]


_LANDMARK_MEMO: list[tuple[np.ndarray, object, float | None, object]] = []


def landmarks_for(scan: RadarScan, config: object = None, max_range_m: float | None = None) -> object:
    """``detect_landmarks(scan, config, max_range_m)``, memoised for the last few scans: the benchmark hands the
    same scan object to every method, and every ReRadar model needs the same Cen 2018 landmarks."""
    from reradar_core.landmarks import Cen2018Config, detect_landmarks

    config = config if config is not None else Cen2018Config()
    for power, cfg, rng, lm in _LANDMARK_MEMO:
        if power is scan.power and cfg == config and rng == max_range_m:
            return lm
    lm = detect_landmarks(scan, config, max_range_m)  # type: ignore[arg-type]
    _LANDMARK_MEMO.append((scan.power, config, max_range_m, lm))
    del _LANDMARK_MEMO[:-4]
    return lm


__all__ += ["landmarks_for"]
