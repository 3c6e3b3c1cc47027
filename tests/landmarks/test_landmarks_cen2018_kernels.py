"""Compiled Cen 2018 detector: the band outside which x = q / sigma_q alone decides, and agreement with the
vectorised (OpenCV) detector up to float32 rounding at the threshold."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.io.scan import RadarScan
from reradar_core.jit import jit_enabled
from reradar_core.landmarks import Cen2018Config, cen2018_response, detect_landmarks
from reradar_core.landmarks.cen2018_kernels import certain_band


def _response(x: np.ndarray, p: np.ndarray) -> np.ndarray:
    d = x - p
    return x - d * np.exp(-0.5 * d * d) - p * np.exp(-0.5 * p * p)


@pytest.mark.parametrize("z_q", [1.0, 3.0, 4.5])
def test_certain_band_bounds_the_response_for_every_smoothed_value(z_q):
    lo, hi = certain_band(z_q)
    assert z_q - 1.22 < lo < z_q < hi < z_q + 1.22  # |y - x| <= 2 exp(-1/2) for every p
    p = np.linspace(-30, 30, 600_001)
    assert _response(lo, p).max() <= z_q  # at (and below: y grows with x) x_lo no p reaches the threshold
    assert _response(hi, p).min() > z_q  # at and above x_hi every p exceeds it
    # the band is tight: within 0.02 of where some p (or every p) crosses the threshold
    assert _response(lo + 0.02, p).max() > z_q
    assert _response(hi - 0.02, p).min() <= z_q


def test_certain_band_at_the_paper_threshold():
    lo, hi = certain_band(3.0)
    assert lo == pytest.approx(2.3935, abs=2e-3) and hi == pytest.approx(3.7053, abs=2e-3)


def _busy_scan(seed: int, n_az: int = 48, n_bins: int = 2000) -> RadarScan:
    """Speckle with extended targets of many strengths, so that many bins lie near the threshold."""
    rng = np.random.default_rng(seed)
    power = rng.gamma(2.0, 0.025, size=(n_az, n_bins))
    for row in range(n_az):
        for _ in range(8):
            c, w = int(rng.integers(60, n_bins - 60)), int(rng.integers(1, 40))
            power[row, c - w: c + w] += rng.uniform(0.02, 0.5)
    return RadarScan.from_power(np.clip(power, 0, 1).astype(np.float32), "boreas")


@pytest.mark.skipif(not jit_enabled(), reason="numba not installed (only the vectorised detector runs)")
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
@pytest.mark.parametrize("max_range_m", [None, 40.0])
def test_compiled_detector_agrees_with_the_vectorised_one(monkeypatch, seed, max_range_m):
    """The same keypoints, except where the response lies within float32 rounding of the threshold; the same
    strengths to float32 rounding."""
    scan = _busy_scan(seed)
    scan.valid[5] = False
    monkeypatch.setenv("RERADAR_JIT", "0")
    want = detect_landmarks(scan, max_range_m=max_range_m)
    monkeypatch.setenv("RERADAR_JIT", "1")
    got = detect_landmarks(scan, max_range_m=max_range_m)
    assert len(want) > 100
    a = set(zip(want.azimuth_index.tolist(), want.range_bin.tolist(), strict=True))
    b = set(zip(got.azimuth_index.tolist(), got.range_bin.tolist(), strict=True))
    assert 5 not in {r for r, _ in b}
    differing = a ^ b
    assert len(differing) <= 2
    if differing:  # each run that differs has a bin whose response is at the threshold to ~1e-5
        y, threshold = cen2018_response(scan.power)
        margin = np.abs(y / threshold[:, None] - 1.0)
        for r, c in differing:
            assert margin[r, max(c - 40, 0): c + 40].min() < 1e-5
    else:
        np.testing.assert_array_equal(got.azimuth_index, want.azimuth_index)
        np.testing.assert_array_equal(got.range_bin, want.range_bin)
        np.testing.assert_allclose(got.strength, want.strength, rtol=1e-5)
        np.testing.assert_array_equal(got.xy_m, want.xy_m)


@pytest.mark.skipif(not jit_enabled(), reason="numba not installed (only the vectorised detector runs)")
def test_compiled_detector_follows_a_run_past_the_tested_bins(monkeypatch):
    """A range-limited detection tests the first bins only; a run through the last of them is followed to its
    end, so its middle (and whether it lies within the range) is the whole row's."""
    rng = np.random.default_rng(7)
    power = np.clip(rng.gamma(2.0, 0.025, size=(4, 1200)), 0, 1).astype(np.float32)
    power[1, 200:420] = 0.95  # middle bin 310 (~18.5 m), end ~25 m: inside a 20 m detection
    power[2, 250:900] = 0.95  # middle beyond 20 m
    scan = RadarScan.from_power(power, "boreas")
    monkeypatch.setenv("RERADAR_JIT", "1")
    near = detect_landmarks(scan, max_range_m=20.0)
    full = detect_landmarks(scan)
    keys = set(zip(near.azimuth_index.tolist(), near.range_bin.tolist(), strict=True))
    assert (1, 310) in keys and not any(r == 2 for r, _ in keys)
    assert keys == {k for k, m in zip(zip(full.azimuth_index.tolist(), full.range_bin.tolist(), strict=True),
                                      full.range_m <= 20.0, strict=True) if m}
    capped = detect_landmarks(scan, Cen2018Config(max_keypoints=3))
    assert len(capped) == 3 and np.all(np.diff(capped.strength) <= 0)
