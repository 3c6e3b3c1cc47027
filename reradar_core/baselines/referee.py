"""ReFeree: free-space descriptor for place recognition plus an initial-heading estimate.

Reference:
    H. Kim, B. Choi, E. Choi and A. Kim, "ReFeree: Radar-Based Lightweight and Robust Localization Using
    Feature and Free Space", IEEE RA-L 2024. Features are Cen 2018 detections on the polar scan; along every
    azimuth the *free space* is the range between the sensor (after the detector's minimum range) and the
    first feature. The place descriptor counts free space per range block (80 blocks, rotation-invariant);
    the heading comes from the per-sector free-space ratios, compared by circular cross-correlation.
    ReFeree estimates no translation, so the paper (Sec. Evaluation Metrics) counts a success as a correct
    retrieval with rotation error below 10 degrees.

Beams with no feature are free up to the maximum range. Distances are Euclidean on the ring descriptor.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from reradar_core.baselines.base import PlaceRecognitionMethod, Prepared, landmarks_for
from reradar_core.io.scan import RadarScan
from reradar_core.landmarks import Cen2018Config

__all__ = ["ReFereeConfig", "ReFeree", "free_space_ranges"]


@dataclass(frozen=True)
class ReFereeConfig:
    """ReFeree settings: 80 range blocks for the place descriptor, sectors for the heading (1 degree each)."""

    num_range_blocks: int = 80
    num_sectors: int = 360
    z_q: float = 3.0
    sigma_bins: int = 17


def free_space_ranges(scan: RadarScan, config: ReFereeConfig = ReFereeConfig()) -> tuple[np.ndarray, int]:
    """Per-azimuth free-space extent: (A,) int64 first-feature range bin (R where a beam has no feature),
    and the detector's minimum range bin (free space starts there)."""
    cen = Cen2018Config(z_q=config.z_q, sigma_bins=config.sigma_bins)
    lm = landmarks_for(scan, cen)
    n_az, n_bins = scan.power.shape
    first = np.full(n_az, n_bins, dtype=np.int64)
    if len(lm):
        np.minimum.at(first, lm.azimuth_index.astype(np.int64), lm.range_bin.astype(np.int64))
    from reradar_core.io.presets import get_preset

    min_range = get_preset(scan.preset).landmark_min_range_bins if scan.preset else 0
    return first, int(min(min_range, n_bins))


class ReFeree(PlaceRecognitionMethod):
    """Free-space ring descriptor (retrieval) + sector free-space ratios (heading)."""

    name = "referee"
    provides_heading = True

    def __init__(self, config: ReFereeConfig = ReFereeConfig()) -> None:
        self.config = config

    def params(self) -> dict[str, Any]:
        c = self.config
        return {"blocks": c.num_range_blocks, "sectors": c.num_sectors, "z_q": c.z_q, "sigma": c.sigma_bins,
                "v": 1}

    def prepare(self, scan: RadarScan) -> Prepared:
        first, lo = free_space_ranges(scan, self.config)
        n_az, n_bins = scan.power.shape
        edges = np.linspace(0, n_bins, self.config.num_range_blocks + 1)
        # free bins of each beam inside each block [e0, e1): overlap of [lo, first) with the block
        e0, e1 = edges[:-1][None], edges[1:][None]
        start = np.full((n_az, 1), float(lo))
        stop = np.maximum(first[:, None].astype(np.float64), start)
        overlap = np.clip(np.minimum(stop, e1) - np.maximum(start, e0), 0.0, None)
        ring = (overlap.sum(0) / (n_az * (e1 - e0)[0])).astype(np.float32)  # free fraction per block
        ratio = ((first - lo).clip(0) / max(n_bins - lo, 1)).astype(np.float32)  # (A,) per-azimuth ratio
        sectors = cv2.resize(ratio[:, None], (1, self.config.num_sectors), interpolation=cv2.INTER_AREA)[:, 0]
        return {"ring": ring, "sectors": sectors.astype(np.float32)}

    def describe_prepared(self, prepared: Prepared) -> np.ndarray:
        return np.concatenate([prepared["ring"], prepared["sectors"]]).astype(np.float32)

    def build_index(self, db_descs: Any) -> Any:
        return np.stack([np.asarray(d, dtype=np.float32) for d in db_descs])

    def distance(self, q_desc: np.ndarray, index: Any) -> np.ndarray:
        nb = self.config.num_range_blocks
        diff = np.asarray(index[:, :nb], dtype=np.float64) - q_desc[None, :nb].astype(np.float64)
        return np.linalg.norm(diff, axis=1)

    def estimate_heading(self, q_desc: np.ndarray, index: Any, j: int) -> float | None:
        nb = self.config.num_range_blocks
        q = q_desc[nb:].astype(np.float64)
        d = np.asarray(index[j, nb:], dtype=np.float64)
        q, d = q - q.mean(), d - d.mean()
        # c[s] = sum_a q[a] d[a - s]: a yaw of +theta (CCW) shifts azimuths (clockwise) by +theta
        corr = np.fft.irfft(np.fft.rfft(q) * np.conj(np.fft.rfft(d)), n=q.size)
        s = int(np.argmax(corr))
        return float(np.mod(s * 2.0 * np.pi / q.size + np.pi, 2.0 * np.pi) - np.pi)
