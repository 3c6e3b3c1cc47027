"""Scan statistics used to calibrate the simulator against real scans (``reradar sim-report``)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from reradar_core.io.scan import RadarScan

__all__ = ["ScanStats", "scan_statistics", "summarize", "RANGE_BANDS_M"]

#: Range bands (metres) of the mean-power profile.
RANGE_BANDS_M = ((0.0, 2.0), (2.0, 5.0), (5.0, 10.0), (10.0, 25.0), (25.0, 50.0), (50.0, 100.0), (100.0, 165.0))


@dataclass
class ScanStats:
    """Per-scan figures (power is the scan's [0, 1] value).

    Attributes:
        mean, p50, p90, p99, p999: power mean and percentiles.
        frac_zero: fraction of bins at exactly 0.
        frac_above_floor: fraction of bins above the noise floor, taken as the 90th percentile of the far
            quarter of the range bins (which holds mostly noise) -- comparable across real and simulated.
        keypoints: Cen 2018 landmarks (z_q = 3, sigma = 17 bins, preset minimum range).
        band_mean: mean power in each ``RANGE_BANDS_M`` band.
        hist: 16-bin intensity histogram over [0, 1] (fractions).
    """

    mean: float
    p50: float
    p90: float
    p99: float
    p999: float
    frac_zero: float
    frac_above_floor: float
    keypoints: int
    band_mean: list[float]
    hist: list[float]

    def as_dict(self) -> dict:
        return asdict(self)


def scan_statistics(scan: RadarScan, with_keypoints: bool = True) -> ScanStats:
    """Statistics of one scan (see ``ScanStats``)."""
    p = scan.power
    q = np.percentile(p, [50, 90, 99, 99.9])
    far = p[:, int(0.75 * p.shape[1]):]
    floor = float(np.percentile(far, 90))
    r = scan.ranges_m
    bands = []
    for lo, hi in RANGE_BANDS_M:
        m = (r >= lo) & (r < hi)
        bands.append(float(p[:, m].mean()) if np.any(m) else float("nan"))
    kp = 0
    if with_keypoints:
        from reradar_core.landmarks import detect_landmarks

        kp = len(detect_landmarks(scan).range_bin)
    hist = np.histogram(p, bins=16, range=(0.0, 1.0))[0] / p.size
    return ScanStats(float(p.mean()), float(q[0]), float(q[1]), float(q[2]), float(q[3]), float((p == 0).mean()),
                     float((p > floor).mean()), int(kp), bands, hist.tolist())


def summarize(stats: list[ScanStats]) -> dict[str, float | list[float]]:
    """Mean over scans of every field (lists averaged element-wise)."""
    out: dict[str, float | list[float]] = {}
    for name in ScanStats.__dataclass_fields__:
        vals = [getattr(s, name) for s in stats]
        out[name] = np.mean(np.asarray(vals, dtype=np.float64), axis=0).tolist()
    return out
