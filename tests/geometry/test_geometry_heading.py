"""The canonical heading (geometry.heading): known answers on constructed scans, and equivariance under turns."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.geometry.cartesian import CartesianConfig, metric_to_pixel, polar_to_cartesian
from reradar_core.geometry.heading import canonical_turn, turn_scan
from reradar_core.io.scan import RadarScan

N_AZ = 400
STEP = 2 * np.pi / N_AZ


def _scan_with_beams(azimuths_rad: list[float], range_m: tuple[float, float] = (10.0, 40.0),
                     first_azimuth: float = 0.0) -> RadarScan:
    """A blank Oxford-preset scan with bright beams (whole rows over ``range_m``) at the given azimuths."""
    scan = RadarScan.from_power(np.zeros((N_AZ, 3768), np.float32), "oxford")
    scan.azimuths = np.mod(first_azimuth + np.arange(N_AZ) * STEP, 2 * np.pi)
    b0, b1 = (int(round((r - scan.range_offset_m) / scan.range_resolution_m)) for r in range_m)
    for a in azimuths_rad:
        scan.power[int(round(np.mod(a - first_azimuth, 2 * np.pi) / STEP)) % N_AZ, b0:b1] = 1.0
    return scan


def _mod90(a: float) -> float:
    """Angle (rad) wrapped to [-pi/4, pi/4)."""
    return float(np.mod(a + np.pi / 4, np.pi / 2) - np.pi / 4)


@pytest.mark.parametrize("alpha_deg", [0.0, 9.0, 22.5, 36.0, -27.0])
def test_four_walls_at_right_angles_give_their_heading(alpha_deg):
    """Four beams 90 degrees apart at alpha (clockwise azimuth): psi = alpha, so the turn is -alpha (mod 90)."""
    alpha = np.deg2rad(alpha_deg)
    scan = _scan_with_beams([alpha + k * np.pi / 2 for k in range(4)])
    assert _mod90(canonical_turn(scan, 64.0) + alpha) == pytest.approx(0.0, abs=1e-9)


def test_beyond_the_image_or_in_the_mount_is_not_seen():
    """A beam at 18 deg inside the image's range and one at 0 deg only beyond it: the turn follows the first."""
    scan = _scan_with_beams([np.deg2rad(18.0)])
    far = _scan_with_beams([0.0], range_m=(80.0, 120.0))
    scan.power += far.power
    assert _mod90(canonical_turn(scan, 64.0) + np.deg2rad(18.0)) == pytest.approx(0.0, abs=1e-9)


def test_a_scan_without_fourfold_structure_turns_by_nothing():
    assert canonical_turn(RadarScan.from_power(np.zeros((N_AZ, 3768), np.float32), "oxford"), 64.0) == 0.0
    uniform = RadarScan.from_power(np.full((N_AZ, 3768), 0.3, np.float32), "oxford")
    assert canonical_turn(uniform, 64.0) == 0.0
    assert canonical_turn(_scan_with_beams([0.3]), 1.0) == 0.0  # no range bin within the profile's reach


@pytest.mark.parametrize("theta_deg", [3.3, 17.0, 61.0, 133.0, 251.0, -40.0])
def test_turning_the_sensor_turns_the_canonical_heading_with_it(theta_deg):
    """Equivariance: the sensor yawed by theta relabels azimuths a + theta; its canonical turn is the old one minus
    theta (mod 90), so both reach the same canonical scan."""
    rng = np.random.default_rng(4)
    scan = RadarScan.from_power(rng.random((N_AZ, 3768), dtype=np.float32) ** 4, "oxford")
    theta = np.deg2rad(theta_deg)
    t0 = canonical_turn(scan, 64.0)
    t1 = canonical_turn(turn_scan(scan, theta), 64.0)
    assert _mod90(t1 - (t0 - theta)) == pytest.approx(0.0, abs=1e-9)
    a = turn_scan(scan, t0).azimuths
    b = turn_scan(turn_scan(scan, theta), t1).azimuths
    assert _mod90(float(np.angle(np.mean(np.exp(1j * (b - a)))))) == pytest.approx(0.0, abs=1e-9)


def test_turn_scan_moves_a_target_to_the_turned_sensor_frame():
    """A target at sensor-frame xy is, in the image of the scan turned by yaw, at R(-yaw) xy."""
    cfg = CartesianConfig(201, 0.64)
    yaw = np.deg2rad(30.0)
    # target at 30 m, clockwise azimuth 50 deg: sensor-frame (x, y) = r (cos a, -sin a)
    a, r = np.deg2rad(50.0), 30.0
    scan = _scan_with_beams([a], range_m=(29.5, 30.5))
    img = polar_to_cartesian(turn_scan(scan, yaw), cfg)
    xy = r * np.array([np.cos(a), -np.sin(a)])
    c, s = np.cos(yaw), np.sin(yaw)
    expected = metric_to_pixel((np.array([[c, s], [-s, c]]) @ xy)[None], cfg)[0]
    peak = np.unravel_index(np.argmax(img), img.shape)
    assert np.hypot(*(np.asarray(peak) - expected)) <= 1.5
    assert turn_scan(scan, 0.0) is scan
