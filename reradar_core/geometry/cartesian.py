"""Polar radar scan -> Cartesian bird's-eye image, and pixel <-> metric conversions.

Image convention (sensor frame x forward, y left): the sensor sits at the image centre
c = (W - 1) / 2; row i, column j has its centre at x = (c - i) * res, y = (c - j) * res, so forward is up
and the vehicle's left is on the image's left. A polar return at azimuth a (clockwise from +x) and range r
is at x = r cos a, y = -r sin a.

Default size: the paper (Sec. Implementation Details) uses 200 x 200 px at 0.64 m/px (128 m across). We
default to 201 x 201 at 0.64 m/px: the C8 backbone's strided layers are exactly equivariant to 90 degree
rotations only when every strided layer sees an odd-sized input, which a side = 1 (mod 8) guarantees
(docs/MODEL.md shows the difference). ``CartesianConfig.paper()`` gives the paper's 200 x 200.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from reradar_core.errors import ConfigError
from reradar_core.io.scan import RadarScan, require_scan

__all__ = [
    "CartesianConfig",
    "polar_to_cartesian",
    "polar_to_metric",
    "metric_to_pixel",
    "pixel_to_metric",
]


@dataclass(frozen=True)
class CartesianConfig:
    """Cartesian image geometry.

    Attributes:
        width_px: image side in pixels (square image). Default 201 (see module docstring).
        resolution_m: metres per pixel. Default 0.64 (paper, Sec. Implementation Details).
    """

    width_px: int = 201
    resolution_m: float = 0.64

    def __post_init__(self) -> None:
        if isinstance(self.width_px, bool) or not isinstance(self.width_px, (int, np.integer)):
            raise ConfigError(f"Cartesian width must be a whole number of pixels, got {self.width_px!r}")
        if self.width_px < 8 or self.width_px > 4096:
            raise ConfigError(f"Cartesian width must be in [8, 4096] px, got {self.width_px}")
        if not (self.resolution_m > 0 and np.isfinite(self.resolution_m)):
            raise ConfigError(f"Cartesian resolution must be positive and finite (metres per pixel), got "
                              f"{self.resolution_m}")

    @classmethod
    def paper(cls) -> CartesianConfig:
        """The paper's 200 x 200 px at 0.64 m/px."""
        return cls(200, 0.64)

    @property
    def centre_px(self) -> float:
        return (self.width_px - 1) / 2.0

    @property
    def half_extent_m(self) -> float:
        """Distance from the centre to the image edge, metres."""
        return self.width_px * self.resolution_m / 2.0


def polar_to_metric(azimuths: np.ndarray, ranges_m: np.ndarray) -> np.ndarray:
    """(N,) azimuths [rad, clockwise from +x] and ranges [m] -> (N, 2) sensor-frame (x, y) metres."""
    a = np.asarray(azimuths, dtype=np.float64)
    r = np.asarray(ranges_m, dtype=np.float64)
    return np.stack([r * np.cos(a), -r * np.sin(a)], axis=-1)


def metric_to_pixel(xy: np.ndarray, config: CartesianConfig = CartesianConfig()) -> np.ndarray:
    """(N, 2) sensor-frame metres -> (N, 2) float (row, col) pixel coordinates."""
    xy = np.asarray(xy, dtype=np.float64)
    c = config.centre_px
    return np.stack([c - xy[..., 0] / config.resolution_m, c - xy[..., 1] / config.resolution_m], axis=-1)


def pixel_to_metric(rc: np.ndarray, config: CartesianConfig = CartesianConfig()) -> np.ndarray:
    """(N, 2) (row, col) pixel coordinates -> (N, 2) sensor-frame (x, y) metres."""
    rc = np.asarray(rc, dtype=np.float64)
    c = config.centre_px
    return np.stack([(c - rc[..., 0]) * config.resolution_m, (c - rc[..., 1]) * config.resolution_m], axis=-1)


@lru_cache(maxsize=32)
def _polar_grid(width_px: int, resolution_m: float, range_res: float, range_offset: float,
                num_bins: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Cached per-pixel (azimuth [rad, clockwise], fractional range bin) for a geometry, and how many leading
    range bins the bilinear sampling can read (the rest of a scan is never looked at)."""
    cfg = CartesianConfig(width_px, resolution_m)
    rows, cols = np.meshgrid(np.arange(width_px), np.arange(width_px), indexing="ij")
    xy = pixel_to_metric(np.stack([rows, cols], axis=-1).astype(np.float64), cfg)
    rng = np.hypot(xy[..., 0], xy[..., 1])
    az = np.mod(np.arctan2(-xy[..., 1], xy[..., 0]), 2.0 * np.pi)
    bin_idx = (rng - range_offset) / range_res
    bin_idx[(bin_idx < 0) | (bin_idx > num_bins - 1)] = -10.0  # outside the scan -> border (0)
    az.setflags(write=False)
    bin_idx = bin_idx.astype(np.float32)
    bin_idx.setflags(write=False)
    # remap rounds a coordinate to 1/32 px, so it reads bins floor(b) .. floor(b) + 2 at most: with two more
    # bins every tap inside the scan is inside the cropped scan too (the same samples, the same code path)
    used = int(min(num_bins, math.floor(float(bin_idx.max())) + 3)) if bin_idx.size else num_bins
    return az, bin_idx, max(used, 1)


@lru_cache(maxsize=8)
def _row_map(width_px: int, resolution_m: float, range_res: float, range_offset: float, num_bins: int,
             first_azimuth: float, step: float, n_az: int) -> np.ndarray:
    """Cached fractional azimuth row of every pixel (``polar_to_cartesian``) for one azimuth table (scans of
    one sensor mostly share it)."""
    az = _polar_grid(width_px, resolution_m, range_res, range_offset, num_bins)[0]
    row = np.mod((az - first_azimuth) / step, n_az).astype(np.float32)
    row.setflags(write=False)
    return row


def polar_to_cartesian(scan: RadarScan, config: CartesianConfig = CartesianConfig()) -> np.ndarray:
    """Resample a polar scan onto a Cartesian grid (bilinear, as the Oxford/Boreas SDKs do).

    Azimuth rows are located from ``scan.azimuths[0]`` and the mean azimuth step; the last row is
    interpolated with the first across the 360 -> 0 degree seam. Pixels beyond the scan's range are 0.

    Returns:
        (W, W) float32 image in [0, 1], W = ``config.width_px``; layout in the module docstring.
    """
    require_scan(scan, "polar_to_cartesian")
    key = (config.width_px, config.resolution_m, scan.range_resolution_m, scan.range_offset_m,
           scan.num_range_bins)
    _, bin_idx, used = _polar_grid(*key)
    n_az = scan.num_azimuths
    az_unwrapped = np.unwrap(scan.azimuths)
    step = (az_unwrapped[-1] - az_unwrapped[0]) / (n_az - 1) if n_az > 1 else 2 * np.pi
    if not np.isfinite(step) or abs(step) < 1e-9:
        step = 2.0 * np.pi / n_az
    row = _row_map(*key, float(az_unwrapped[0]), float(step), n_az)
    # Append row 0 after the last row so bilinear sampling wraps across the seam; only the range bins the
    # image reaches are copied (~45 % of a Boreas scan at the model's 128 m; the same samples).
    polar = np.vstack([scan.power[:, :used], scan.power[:1, :used]]).astype(np.float32, copy=False)
    return cv2.remap(polar, bin_idx, row, interpolation=cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
