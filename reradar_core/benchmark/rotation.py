"""Rotation stress: the same scan as seen by a sensor turned by a heading offset.

A sensor yawed by +theta (counter-clockwise) relative to the original sees a return at clockwise azimuth
a + theta that the original saw at a, so the polar image is rolled by +theta along azimuth
(docs/CONVENTIONS.md: azimuth clockwise from +x, yaw counter-clockwise). The ground-truth pose of the
rotated scan is ``T_world_sensor' = compose(T_world_sensor, (0, 0, theta))``.
"""

from __future__ import annotations

import numpy as np

from reradar_core.geometry.se2 import compose
from reradar_core.io.scan import RadarScan

__all__ = ["rotate_power", "rotate_scan", "rotate_pose", "heading_offsets"]


def rotate_power(power: np.ndarray, yaw_rad: float) -> np.ndarray:
    """(..., A, R) polar power of one or more scans as seen by the sensor yawed by ``yaw_rad`` (CCW): rolled along
    the azimuth axis (-2) with linear interpolation between rows; same shape, float32."""
    n_az = power.shape[-2]
    shift = float(yaw_rad) / (2.0 * np.pi) * n_az  # rows, may be fractional
    k = int(np.floor(shift))
    frac = shift - k
    rolled = np.roll(power, k, axis=-2)
    if frac > 1e-9:
        rolled = (1.0 - frac) * rolled + frac * np.roll(rolled, 1, axis=-2)
    return np.asarray(rolled, dtype=np.float32)


def rotate_scan(scan: RadarScan, yaw_rad: float) -> RadarScan:
    """The scan seen by the same sensor yawed by ``yaw_rad`` (CCW): ``rotate_power`` of its power (azimuths,
    timestamps and range geometry unchanged)."""
    return scan.with_power(rotate_power(scan.power, yaw_rad))


def rotate_pose(T_world_sensor: np.ndarray, yaw_rad: float | np.ndarray) -> np.ndarray:
    """Ground-truth pose of the rotated sensor: ``compose(T_world_sensor, (0, 0, yaw))``."""
    T = np.asarray(T_world_sensor, dtype=np.float64)
    yaw = np.broadcast_to(np.asarray(yaw_rad, dtype=np.float64), T.shape[:-1])
    d = np.stack([np.zeros_like(yaw), np.zeros_like(yaw), yaw], axis=-1)
    return compose(T, d)


def heading_offsets(n: int, seed: int = 0, num_azimuths: int | None = None) -> np.ndarray:
    """(n,) float64 random heading offsets, uniform in [0, 2 pi) radians (seeded).

    With ``num_azimuths`` the offsets are rounded to whole azimuth steps (2 pi / A), so ``rotate_scan`` is
    an exact re-indexing of the sensor's azimuths: interpolating between rows would smooth the speckle and
    change what intensity-statistics detectors (Cen 2018) see, which is not what turning the sensor does.
    """
    yaw = np.random.default_rng(seed).uniform(0.0, 2.0 * np.pi, size=n)
    if num_azimuths:
        step = 2.0 * np.pi / num_azimuths
        yaw = np.mod(np.round(yaw / step), num_azimuths) * step
    return yaw
