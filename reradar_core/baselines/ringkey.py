"""RingKey: the ring-key part of Scan Context, as used by the OORD benchmark.

References:
    G. Kim and A. Kim, "Scan Context: Egocentric spatial descriptor for place recognition within 3D point
    cloud map", IROS 2018 (ring key = per-ring statistic over all sectors, rotation-invariant).
    M. Gadd et al., "OORD: The Oxford Offroad Radar Dataset", IEEE T-ITS 2024: RingKey on the polar radar
    image resized to 40 azimuths x 120 rings, mean power per ring, Euclidean distance; no Scan Context
    orientation refinement (so no heading and no pose).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from reradar_core.baselines.base import EuclideanIndex, PlaceRecognitionMethod, Prepared, polar_resize
from reradar_core.io.scan import RadarScan

__all__ = ["RingKeyConfig", "RingKey", "ring_key"]


@dataclass(frozen=True)
class RingKeyConfig:
    """OORD benchmark settings: 40 azimuth sectors x 120 range rings."""

    num_sectors: int = 40
    num_rings: int = 120


def ring_key(power: np.ndarray, config: RingKeyConfig = RingKeyConfig()) -> np.ndarray:
    """(A, R) polar power -> (num_rings,) float32 mean power per range ring (rotation-invariant)."""
    small = polar_resize(power, config.num_sectors, config.num_rings)
    return small.mean(axis=0).astype(np.float32)


class RingKey(PlaceRecognitionMethod):
    """Rotation-invariant ring key; Euclidean distance; no heading."""

    name = "ringkey"

    def __init__(self, config: RingKeyConfig = RingKeyConfig()) -> None:
        self.config = config

    def params(self) -> dict[str, Any]:
        return {"sectors": self.config.num_sectors, "rings": self.config.num_rings, "v": 1}

    def prepare(self, scan: RadarScan) -> Prepared:
        return {"key": ring_key(scan.power, self.config)}

    def describe_prepared(self, prepared: Prepared) -> np.ndarray:
        return np.asarray(prepared["key"], dtype=np.float32)

    def build_index(self, db_descs: Any) -> Any:
        return EuclideanIndex(db_descs)

    def distance(self, q_desc: np.ndarray, index: Any) -> np.ndarray:
        return index.distances(q_desc)
