"""Cen 2018 detector: targets found at known positions, min range, cap, invalid azimuths, reference agreement."""

from __future__ import annotations

import math

import numpy as np
import pytest

from reradar_core.errors import ConfigError
from reradar_core.io.scan import RadarScan
from reradar_core.landmarks import Cen2018Config, cen2018_response, detect_landmarks

N_AZ, N_BINS = 32, 3768  # Oxford geometry, fewer azimuths to keep the tests fast


@pytest.fixture(autouse=True, params=["1", "0"], ids=["compiled", "vectorised"])
def _detector_path(request, monkeypatch):
    """Every test runs with the compiled detector (where numba is installed) and the vectorised one."""
    monkeypatch.setenv("RERADAR_JIT", request.param)


def _noise_scan(seed: int = 0, n_az: int = N_AZ, n_bins: int = N_BINS, preset: str = "oxford") -> RadarScan:
    """A speckle-like noise floor (mean ~0.05) like the real Oxford scans (mean power 0.045)."""
    rng = np.random.default_rng(seed)
    power = np.clip(rng.gamma(2.0, 0.025, size=(n_az, n_bins)), 0, 1).astype(np.float32)
    return RadarScan.from_power(power, preset)


def _add_target(scan: RadarScan, row: int, centre_bin: int, half_width: int = 3, value: float = 0.9) -> None:
    scan.power[row, centre_bin - half_width : centre_bin + half_width + 1] = value


def _reference_keypoints(power: np.ndarray, zq: float, sigma: int, min_range: int) -> set[tuple[int, int]]:
    """Straight transcription of the published per-bin loops (yeti ``cen2018features``), for small arrays."""
    power = power.astype(np.float64)
    fsize = sigma * 3
    mu = fsize // 2
    kernel = np.array([math.exp(-0.5 * (i - mu) ** 2 / sigma**2) for i in range(fsize)])
    kernel /= kernel.sum()
    out = set()
    n_bins = power.shape[1]
    for i in range(power.shape[0]):
        q = power[i] - power[i].mean()
        # BORDER_REFLECT101 correlation with the (symmetric) kernel
        p = np.empty(n_bins)
        for j in range(n_bins):
            acc = 0.0
            for k in range(fsize):
                idx = j + k - mu
                if idx < 0:
                    idx = -idx
                elif idx >= n_bins:
                    idx = 2 * (n_bins - 1) - idx
                acc += kernel[k] * q[idx]
            p[j] = acc
        neg = q[q < 0]
        sigma_q = math.sqrt(np.sum(2 * neg**2) / neg.size) if neg.size else 0.034
        peak: list[int] = []
        for j in range(min_range, n_bins):
            nqp = math.exp(-0.5 * ((q[j] - p[j]) / sigma_q) ** 2)
            npp = math.exp(-0.5 * (p[j] / sigma_q) ** 2)
            y = q[j] * (1 - nqp) + p[j] * (nqp - npp)
            if y > zq * sigma_q:
                peak.append(j)
            elif peak:
                out.add((i, peak[len(peak) // 2]))
                peak = []
        if peak:
            out.add((i, peak[len(peak) // 2]))
    return out


def test_matches_reference_transcription():
    scan = _noise_scan(1, n_az=4, n_bins=400)
    scan.power[1, 100:106] = 0.8
    scan.power[2, 300:302] = 0.7
    scan.power[3, 395:] = 0.9  # a run touching the last bin
    cfg = Cen2018Config(min_range_bins=20)
    got = detect_landmarks(scan, cfg)
    ours = set(zip(got.azimuth_index.tolist(), got.range_bin.tolist(), strict=True))
    ref = _reference_keypoints(scan.power, 3.0, 17, 20)
    assert ours == ref
    assert (1, 103) in ours and (3, 397) in ours  # middle element (index len // 2) of each run


def test_targets_found_at_known_positions():
    scan = _noise_scan(2)
    targets = [(0, 300), (5, 800), (11, 1500), (20, 2500), (31, 3600)]
    for row, b in targets:
        _add_target(scan, row, b)
    lm = detect_landmarks(scan)
    for row, b in targets:
        on_row = lm.range_bin[lm.azimuth_index == row]
        assert np.min(np.abs(on_row - b)) <= 3, (row, b, on_row)
    # positions are consistent with the scan geometry and the clockwise-azimuth convention
    k = np.flatnonzero((lm.azimuth_index == 5) & (np.abs(lm.range_bin - 800) <= 3))[0]
    a = scan.azimuths[5]
    r = lm.range_bin[k] * scan.range_resolution_m
    np.testing.assert_allclose(lm.range_m[k], r)
    np.testing.assert_allclose(lm.xy_m[k], [r * np.cos(a), -r * np.sin(a)])
    assert lm.xy_m.shape == (len(lm), 2) and lm.xy_m.dtype == np.float64
    assert lm.strength.dtype == np.float32 and np.all(lm.strength > 0)


def test_pure_noise_gives_few_keypoints_and_targets_stand_out():
    scan = _noise_scan(3)
    n_noise = len(detect_landmarks(scan))
    _add_target(scan, 7, 2000, value=1.0)
    lm = detect_landmarks(scan)
    strongest = np.argmax(lm.strength)
    assert lm.azimuth_index[strongest] == 7 and abs(lm.range_bin[strongest] - 2000) <= 3
    assert n_noise < N_AZ * 60  # sparse: far below one detection per 60 bins per azimuth


def test_nothing_below_min_range():
    scan = _noise_scan(4)
    _add_target(scan, 3, 30)  # inside the Oxford preset's 58-bin minimum range
    _add_target(scan, 4, 57)
    lm = detect_landmarks(scan)
    assert lm.range_bin.min() >= 58
    lm_boreas = detect_landmarks(_noise_scan(4, n_bins=3360, preset="boreas"))
    assert lm_boreas.range_bin.min() >= 42
    explicit = detect_landmarks(scan, Cen2018Config(min_range_bins=20))
    assert np.any((explicit.azimuth_index == 3) & (np.abs(explicit.range_bin - 30) <= 3))
    assert explicit.range_bin.min() >= 20


def test_max_keypoints_keeps_the_strongest():
    scan = _noise_scan(5)
    for row in range(0, N_AZ, 4):
        _add_target(scan, row, 1000 + 50 * row, value=1.0)
    full = detect_landmarks(scan)
    capped = detect_landmarks(scan, Cen2018Config(max_keypoints=8))
    assert len(capped) == 8 < len(full)
    assert np.all(np.diff(capped.strength) <= 0)  # strongest first
    np.testing.assert_allclose(capped.strength, np.sort(full.strength)[::-1][:8])
    assert set(capped.azimuth_index.tolist()) == set(range(0, N_AZ, 4))  # the planted targets win
    assert len(detect_landmarks(scan, Cen2018Config(max_keypoints=0))) == 0
    assert len(detect_landmarks(scan, Cen2018Config(max_keypoints=10**6))) == len(full)


def test_invalid_azimuths_are_skipped():
    scan = _noise_scan(6)
    _add_target(scan, 9, 1200, value=1.0)
    _add_target(scan, 10, 1300, value=1.0)
    scan.valid[9] = False
    lm = detect_landmarks(scan)
    assert not np.any(lm.azimuth_index == 9)
    assert np.any((lm.azimuth_index == 10) & (np.abs(lm.range_bin - 1300) <= 3))


def test_flat_rows_use_fallback_sigma_and_yield_nothing():
    scan = RadarScan.from_power(np.full((N_AZ, N_BINS), 0.3, np.float32), "oxford")
    assert len(detect_landmarks(scan)) == 0
    y, thr = cen2018_response(scan.power)
    np.testing.assert_allclose(thr, 3.0 * 0.034, rtol=1e-6)
    assert np.all(y == 0)


def test_response_threshold_matches_definition():
    scan = _noise_scan(7, n_az=3, n_bins=500)
    y, thr = cen2018_response(scan.power)
    q = scan.power.astype(np.float64) - scan.power.mean(axis=1, keepdims=True)
    neg = np.where(q < 0, q, 0.0)
    sigma_q = np.sqrt(2 * np.sum(neg**2, axis=1) / np.sum(q < 0, axis=1))
    np.testing.assert_allclose(thr, 3.0 * sigma_q, rtol=1e-4)
    assert y.shape == scan.power.shape and y.dtype == np.float32


def test_repeated_calls_and_shape_changes_are_independent():
    a = _noise_scan(8)
    b = _noise_scan(9, n_az=16, n_bins=3360, preset="boreas")
    first = detect_landmarks(a)
    detect_landmarks(b)
    again = detect_landmarks(a)
    np.testing.assert_array_equal(first.azimuth_index, again.azimuth_index)
    np.testing.assert_array_equal(first.range_bin, again.range_bin)
    np.testing.assert_array_equal(first.strength, again.strength)


def test_config_validation():
    with pytest.raises(ConfigError):
        Cen2018Config(z_q=0)
    with pytest.raises(ConfigError):
        Cen2018Config(sigma_bins=0)
    with pytest.raises(ConfigError):
        Cen2018Config(min_range_bins=-1)
    with pytest.raises(ConfigError):
        Cen2018Config(max_keypoints=-5)
    cfg = Cen2018Config()
    assert (cfg.z_q, cfg.sigma_bins, cfg.min_range_bins, cfg.max_keypoints) == (3.0, 17, None, None)


def test_concurrent_calls_agree_with_sequential():
    """The shared scratch workspace must not leak results between threads (threaded service)."""
    from concurrent.futures import ThreadPoolExecutor

    scans = [_noise_scan(10 + i) for i in range(4)]
    for i, s in enumerate(scans):
        _add_target(s, i, 900 + 100 * i)
    expected = [detect_landmarks(s) for s in scans]
    with ThreadPoolExecutor(max_workers=4) as pool:
        results = list(pool.map(detect_landmarks, scans * 3))
    for k, got in enumerate(results):
        want = expected[k % 4]
        np.testing.assert_array_equal(got.azimuth_index, want.azimuth_index)
        np.testing.assert_array_equal(got.range_bin, want.range_bin)
        np.testing.assert_array_equal(got.strength, want.strength)


def _fields(lm) -> list[bytes]:
    return [np.asarray(getattr(lm, a)).tobytes() for a in
            ("azimuth_index", "range_bin", "azimuth_rad", "range_m", "xy_m", "strength")]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_max_range_gives_exactly_the_near_landmarks(seed):
    """A range-limited detection (response computed on the first bins only, whole rows where a run reaches
    the edge of those) returns the full detection's landmarks within the range, bit for bit, in order."""
    scan = _noise_scan(seed, n_az=24, n_bins=1200, preset="boreas")
    res = scan.range_resolution_m
    rng = np.random.default_rng(seed)
    for row in range(0, 24, 2):  # targets everywhere, some long runs across the ranges tried below
        centre = int(rng.integers(60, 1150))
        scan.power[row, centre - 40: centre + 40] = 0.9
    full = detect_landmarks(scan)
    assert len(full) > 50
    edges = [scan.range_offset_m + b * res for b in (300, 301, 500, 700)]
    for max_range in [0.0, 5.0, 18.3, 31.7, 45.0, *edges, 70.0, 1e6]:
        near = full.subset(full.range_m <= max_range)
        assert _fields(detect_landmarks(scan, max_range_m=max_range)) == _fields(near), max_range


def test_max_range_with_a_run_through_the_computed_edge():
    scan = _noise_scan(5, n_az=8, n_bins=1200, preset="boreas")
    scan.power[3, 250:900] = 0.95  # one run far past the edge of a 20 m detection: its middle is beyond it
    scan.power[5, 200:420] = 0.95  # its middle (bin 310, ~18.5 m) is within 20 m, its end (~25 m) is not
    full = detect_landmarks(scan)
    near = detect_landmarks(scan, max_range_m=20.0)
    assert _fields(near) == _fields(full.subset(full.range_m <= 20.0))
    assert (5, 310) in set(zip(near.azimuth_index.tolist(), near.range_bin.tolist(), strict=True))
    capped = Cen2018Config(max_keypoints=10)  # a cap picks among all landmarks: the range filters after it
    full_c = detect_landmarks(scan, capped)
    assert _fields(detect_landmarks(scan, capped, 20.0)) == _fields(full_c.subset(full_c.range_m <= 20.0))
