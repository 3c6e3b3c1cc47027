"""RingKey: the ring-key part of Scan Context, as the OORD benchmark computes it.

References:
    G. Kim and A. Kim, "Scan Context: Egocentric spatial descriptor for place recognition within 3D point
    cloud map", IROS 2018 (ring key = per-ring statistic over all sectors, rotation-invariant).
    Reference implementation: OORD benchmark code, github.com/mttgdd/oord-dataset at commit
    f04683fb68d15f042395de528c92064dbfc4bc30: ``config/ringkey.yaml`` (min_bin 60, max_bin 3768, polar,
    num_azis = num_bins = 256), ``src/dataset.py`` (``load_image``), ``src/ringkey.py`` (``RingKey``),
    ``jobs/test_ringkey.py``, ``src/compute_distance_matrix.py`` (Euclidean ``cdist``).

Pipeline: bins < 60 zeroed, bins >= 3768 cut; the polar image resized (Pillow bicubic) to 256 azimuths x 256
bins; that image resized again (Pillow bicubic) to 40 azimuths x 120 rings; the mean over the 40 azimuths
per ring -> 120 values; Euclidean distance. No Scan Context orientation refinement (no heading, no pose).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from PIL import Image

from reradar_core.baselines.base import EuclideanIndex, PlaceRecognitionMethod, Prepared
from reradar_core.baselines.oord import MAX_BIN, MIN_BIN, oord_polar_image
from reradar_core.io.scan import RadarScan

__all__ = ["RingKeyConfig", "RingKey", "ring_key"]


@dataclass(frozen=True)
class RingKeyConfig:
    """OORD settings: 256 x 256 polar image, then 40 azimuth sectors x 120 range rings; bins [60, 3768)."""

    image_azimuths: int = 256
    image_bins: int = 256
    num_sectors: int = 40
    num_rings: int = 120
    min_bin: int = MIN_BIN
    max_bin: int = MAX_BIN


def ring_key(power: np.ndarray, config: RingKeyConfig = RingKeyConfig()) -> np.ndarray:
    """(A, R) polar power in [0, 1] -> (num_rings,) float32 mean power per range ring (rotation-invariant)."""
    img = oord_polar_image(power, config.image_azimuths, config.image_bins, config.min_bin, config.max_bin)
    small = Image.fromarray(img).resize((config.num_rings, config.num_sectors), Image.Resampling.BICUBIC)
    return np.asarray(small, dtype=np.float32).mean(axis=0).astype(np.float32)


class RingKey(PlaceRecognitionMethod):
    """Rotation-invariant ring key; Euclidean distance; no heading."""

    name = "ringkey"
    algorithm_version = 2

    def __init__(self, config: RingKeyConfig = RingKeyConfig()) -> None:
        self.config = config

    def params(self) -> dict[str, Any]:
        c = self.config
        return {"image": [c.image_azimuths, c.image_bins], "sectors": c.num_sectors, "rings": c.num_rings,
                "min_bin": c.min_bin, "max_bin": c.max_bin}

    def prepare(self, scan: RadarScan) -> Prepared:
        return {"key": ring_key(scan.power, self.config)}

    def describe_prepared(self, prepared: Prepared) -> np.ndarray:
        return np.asarray(prepared["key"], dtype=np.float32)

    def build_index(self, db_descs: Any) -> Any:
        return EuclideanIndex(db_descs)

    def distance(self, q_desc: np.ndarray, index: Any) -> np.ndarray:
        return index.distances(q_desc)
