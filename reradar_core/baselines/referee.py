"""ReFeree: free-space descriptor for place recognition plus an initial-heading estimate.

References:
    B. Choi, H. Kim and Y. Cho, "ReFeree: Radar-based efficient global descriptor using a Feature and Free
    space for Place Recognition", ICRA 2024 workshop; H. Kim, B. Choi, E. Choi and Y. Cho, RA-L 2024
    (journal version with initial-heading estimation). Layout as the authors' reference implementation
    (github.com/sparolab/referee, ``referee.cpp``):

    - Features: Cen 2018 detections drawn into a binary polar image (A azimuths x R range bins).
    - ReFeree-R (place): per range bin the free-space count (azimuths without a feature), summed over
      windows of 80 range bins -> R // 80 values; similarity = cosine.
    - ReFeree-A (heading): A / 8 azimuth sectors (50 for 400 azimuths, 7.2 degrees each); per sector the
      fraction of range bins up to the farthest feature of each ray; the heading is the circular shift of
      the sectors that maximises the cosine similarity.

ReFeree estimates no translation, so the paper (Sec. Evaluation Metrics) counts a success as a correct
retrieval with rotation error below 10 degrees.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from reradar_core.baselines.base import PlaceRecognitionMethod, Prepared, landmarks_for
from reradar_core.io.scan import RadarScan
from reradar_core.landmarks import Cen2018Config

__all__ = ["ReFereeConfig", "ReFeree", "feature_image"]


@dataclass(frozen=True)
class ReFereeConfig:
    """Reference-implementation settings: 80-bin range windows, 8 azimuth rows per heading sector."""

    range_window_bins: int = 80
    rows_per_sector: int = 8
    z_q: float = 3.0
    sigma_bins: int = 17


def feature_image(scan: RadarScan, config: ReFereeConfig = ReFereeConfig()) -> np.ndarray:
    """(A, R) bool polar image: True at every Cen 2018 feature of the scan."""
    lm = landmarks_for(scan, Cen2018Config(z_q=config.z_q, sigma_bins=config.sigma_bins))
    img = np.zeros(scan.power.shape, dtype=bool)
    img[np.asarray(lm.azimuth_index, np.int64), np.asarray(lm.range_bin, np.int64)] = True
    return img


class ReFeree(PlaceRecognitionMethod):
    """Free-space range descriptor (retrieval, cosine) + sector free-space ratios (heading)."""

    name = "referee"
    provides_heading = True

    def __init__(self, config: ReFereeConfig = ReFereeConfig()) -> None:
        self.config = config

    def params(self) -> dict[str, Any]:
        c = self.config
        return {"window": c.range_window_bins, "rows": c.rows_per_sector, "z_q": c.z_q, "sigma": c.sigma_bins,
                "v": 2}

    def prepare(self, scan: RadarScan) -> Prepared:
        c = self.config
        img = feature_image(scan, c)
        n_az, n_bins = img.shape
        free = (n_az - img.sum(axis=0)).astype(np.float64)  # free azimuths per range bin
        n_win = max(n_bins // c.range_window_bins, 1)
        ring = free[: n_win * c.range_window_bins].reshape(n_win, -1).sum(axis=1)
        # per ray: bins up to (and including) the farthest feature; 0 for rays without a feature
        has = img.any(axis=1)
        far = np.where(has, n_bins - 1 - np.argmax(img[:, ::-1], axis=1), 0).astype(np.float64)
        n_sec = max(n_az // c.rows_per_sector, 1)
        rows = n_sec * c.rows_per_sector
        sectors = far[:rows].reshape(n_sec, -1).sum(axis=1) / (c.rows_per_sector * n_bins)
        return {"ring": ring.astype(np.float32), "sectors": sectors.astype(np.float32)}

    def describe_prepared(self, prepared: Prepared) -> np.ndarray:
        """[n_ring, unit ring descriptor (n_ring), sector ratios]: one flat float32 vector; the leading count
        says where the heading part starts."""
        ring = np.asarray(prepared["ring"], dtype=np.float64)
        ring = ring / max(float(np.linalg.norm(ring)), 1e-12)  # cosine similarity = dot of unit vectors
        return np.concatenate([[ring.size], ring, prepared["sectors"]]).astype(np.float32)

    @staticmethod
    def _split(desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = int(desc[0])
        return desc[1 : 1 + n], desc[1 + n :]

    def distance(self, q_desc: np.ndarray, index: Any) -> np.ndarray:
        ring, _ = self._split(q_desc)
        n = ring.size
        return 1.0 - np.asarray(index[:, 1 : 1 + n], np.float64) @ ring.astype(np.float64)

    def estimate_heading(self, q_desc: np.ndarray, index: Any, j: int) -> float | None:
        _, q = self._split(np.asarray(q_desc, np.float64))
        _, d = self._split(np.asarray(index[j], np.float64))
        # score[s] = sum_a q[a] d[a - s]: a yaw of +theta (CCW) moves azimuths (clockwise) by +theta
        score = np.fft.irfft(np.fft.rfft(q) * np.conj(np.fft.rfft(d)), n=q.size)
        s = int(np.argmax(score))
        return float(np.mod(s * 2.0 * np.pi / q.size + np.pi, 2.0 * np.pi) - np.pi)
