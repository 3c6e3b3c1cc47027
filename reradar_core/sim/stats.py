"""Scan statistics used to calibrate the simulator against real scans (``reradar sim-report``)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from reradar_core.io.scan import RadarScan

__all__ = ["ScanStats", "scan_statistics", "summarize", "RANGE_BANDS_M", "BeamLevelStats", "beam_level_statistics",
           "beam_level_persistence", "BEAM_LEVEL_BANDS_M"]

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


#: Range bands (metres) over which ``beam_level_statistics`` compares whole beams.
BEAM_LEVEL_BANDS_M = ((3.0, 20.0), (20.0, 50.0), (50.0, 100.0), (100.0, 165.0))


@dataclass
class BeamLevelStats:
    """How much the level of whole beams jumps from one azimuth to the next (one scan).

    Every figure is on the high-passed per-azimuth profile (the profile minus its circular 9-azimuth moving mean),
    so the scene's slow changes with the bearing (a façade on one side, open ground on the other) drop out and what
    stays is the beam-to-beam jump. Levels are in 8-bit steps (power x 255). Means, not medians or percentiles:
    real Navtech PNGs quantise low levels coarsely (0, 6, 9, 12, 14, 15, 17, ...: the integer amplitude in dB),
    so a beam's median noise level flips between 0 and 6 where a simulated one moves by single steps.

    Attributes:
        level_jitter: standard deviation of the high-passed per-beam mean over 3-165 m.
        far_jitter: the same over 100-165 m (mostly receiver noise and a few far targets).
        band_coupling: mean correlation, over the pairs of ``BEAM_LEVEL_BANDS_M``, of the high-passed per-beam
            means: near 0 when the jumps come from the scene (independent at different ranges), high when a
            beam's level moves as a whole (a gain of the receiver); 0 where a band has no jump at all.
        lag1: correlation of the high-passed per-beam mean over 3-165 m with its neighbouring azimuth's.
    """

    level_jitter: float
    far_jitter: float
    band_coupling: float
    lag1: float

    def as_dict(self) -> dict:
        return asdict(self)


def _highpass(profile: np.ndarray, width: int = 9) -> np.ndarray:
    """(A,) profile minus its circular ``width``-azimuth moving mean."""
    kernel = np.ones(width) / width
    padded = np.concatenate([profile[-(width // 2):], profile, profile[: width // 2]])
    return profile - np.convolve(padded, kernel, mode="valid")


def _band_profile(scan: RadarScan, lo_m: float, hi_m: float) -> np.ndarray | None:
    """(A,) high-passed per-beam mean power (8-bit steps) over ranges [lo_m, hi_m); None if the scan has none."""
    m = (scan.ranges_m >= lo_m) & (scan.ranges_m < hi_m)
    if not np.any(m):
        return None
    return _highpass(scan.power[:, m].astype(np.float64).mean(axis=1) * 255.0)


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation; 0 where either side is constant (no jump to correlate)."""
    a, b = a - a.mean(), b - b.mean()
    den = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / den) if den > 1e-12 else 0.0


def beam_level_statistics(scan: RadarScan) -> BeamLevelStats:
    """Beam-to-beam level statistics of one scan (see ``BeamLevelStats``); ValueError if it ends before 100 m."""
    whole, far = _band_profile(scan, 3.0, 165.0), _band_profile(scan, 100.0, 165.0)
    if whole is None or far is None:
        raise ValueError(f"scan reaches {scan.ranges_m[-1]:.0f} m: beam-level statistics need ranges beyond 100 m")
    bands = [b for b in (_band_profile(scan, lo, hi) for lo, hi in BEAM_LEVEL_BANDS_M) if b is not None]
    pairs = [_corr(a, b) for i, a in enumerate(bands) for b in bands[i + 1:]]
    coupling = float(np.mean(pairs))
    lag1 = _corr(whole, np.roll(whole, 1))
    return BeamLevelStats(float(whole.std()), float(far.std()), coupling, lag1)


def beam_level_persistence(scans: list[RadarScan], gap: int) -> float:
    """Mean same-azimuth correlation of the high-passed per-beam mean at 100-165 m between scans ``gap`` apart in
    ``scans`` (a drive in order): near 0 when the beam-to-beam jumps are drawn afresh every scan, higher when they
    come from the scene and the scans are close enough to share it."""
    prof: list[np.ndarray] = []
    for s in scans:
        far = _band_profile(s, 100.0, 165.0)
        if far is None:
            raise ValueError("beam-level persistence needs scans with ranges beyond 100 m")
        prof.append(far)
    return float(np.mean([_corr(prof[i], prof[i + gap]) for i in range(len(prof) - gap)]))
