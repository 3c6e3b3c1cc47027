"""Convert polar scans of another layout or resolution into Navtech scans of a preset.

Scans from other radars or tools come without the 11 Navtech metadata columns, transposed (range bins as
rows), with another range-bin size or azimuth count. Read as Navtech PNGs they decode into garbage azimuths
and ranges (the reader refuses them, ``io.scan.check_navtech_layout``); this module resamples them instead:

1. orient the array as (azimuths, range bins) (``azimuth_axis``);
2. resample every beam from the source range grid ``offset + i * resolution`` to the preset's range grid
   (linear interpolation; bins beyond the source's maximum range are 0 = no return);
3. resample the azimuths circularly to the preset's azimuth count when they differ;
4. attach uniform azimuths from ``start_azimuth_rad`` and azimuth timestamps over one sweep.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from reradar_core.errors import ScanFormatError
from reradar_core.io.presets import RadarPreset, get_preset
from reradar_core.io.scan import MIN_SCAN_SIDE, RadarScan, check_scan_sides

__all__ = ["ForeignScanLayout", "RANGE_RESOLUTION_BOUNDS_M", "import_polar_scan"]


#: Range resolutions a source may have, metres per bin (radars: ~0.04-0.5 m): outside, a unit is wrong.
RANGE_RESOLUTION_BOUNDS_M = (1e-3, 10.0)


#: the most negative range of a source's bin 0 accepted, metres (real offsets: Boreas -0.31 m; a few metres
#: behind the antenna is already no radar's)
MIN_RANGE_OFFSET_M = -5.0


@dataclass(frozen=True)
class ForeignScanLayout:
    """How a foreign polar array is laid out.

    Attributes:
        range_resolution_m: metres per range bin of the source (e.g. 0.175).
        range_offset_m: range of the source's bin 0 centre, metres.
        azimuth_axis: array axis that indexes azimuth (0: rows are azimuths, as Navtech; 1: transposed).
        start_azimuth_rad: azimuth of the first source azimuth, radians, clockwise from forward.
    """

    range_resolution_m: float
    range_offset_m: float = 0.0
    azimuth_axis: int = 0
    start_azimuth_rad: float = 0.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.range_resolution_m) and self.range_resolution_m > 0):
            raise ScanFormatError(f"range resolution must be a positive number of metres, got "
                                  f"{self.range_resolution_m}")
        lo, hi = RANGE_RESOLUTION_BOUNDS_M
        if not lo <= self.range_resolution_m <= hi:
            raise ScanFormatError(f"range resolution {self.range_resolution_m:g} m per bin is not a radar's (radars "
                                  f"sample {lo:g}-{hi:g} m per bin; Navtech 0.044-0.175 m): check the unit (metres)")
        if not np.isfinite(self.range_offset_m):
            raise ScanFormatError(f"range offset must be a finite number of metres, got {self.range_offset_m}")
        if self.range_offset_m < MIN_RANGE_OFFSET_M:  # a calibration shift is a fraction of a metre (Boreas -0.31)
            raise ScanFormatError(f"range offset {self.range_offset_m:g} m would put the source's first range bin "
                                  f"{-self.range_offset_m:g} m behind the antenna; a radar's offset is a calibration "
                                  f"shift (Boreas: -0.31 m; accepted down to {MIN_RANGE_OFFSET_M:g} m): check its "
                                  "sign and unit")
        if not np.isfinite(self.start_azimuth_rad):
            raise ScanFormatError(f"start azimuth must be a finite angle, got {self.start_azimuth_rad}")
        if self.azimuth_axis not in (0, 1):
            raise ScanFormatError(f"azimuth_axis must be 0 or 1, got {self.azimuth_axis}")
        # one turn: a start azimuth of 1e17 rad would otherwise lose every digit of the encoder column
        object.__setattr__(self, "start_azimuth_rad", float(np.mod(self.start_azimuth_rad, 2 * np.pi)))


def _to_unit_power(array: np.ndarray) -> np.ndarray:
    if array.dtype == np.uint8:
        return array.astype(np.float32) / 255.0
    if array.dtype.kind not in "uif":
        raise ScanFormatError(f"polar array must be numeric, got dtype {array.dtype}")
    out = array.astype(np.float32)
    if not np.all(np.isfinite(out)) or out.min() < 0 or out.max() > 1:
        raise ScanFormatError("a non-uint8 polar array must hold power as finite fractions of full scale in "
                              "[0, 1]; rescale it first (e.g. divide 16-bit data by 65535)")
    return out


def import_polar_scan(array: np.ndarray, layout: ForeignScanLayout, preset: str | RadarPreset,
                      start_time_us: int = 0) -> RadarScan:
    """Resample a foreign (A, R) or (R, A) polar power array into a scan of ``preset``.

    Args:
        array: 2-D uint8 (0..255) or float in [0, 1] power.
        layout: the source's range grid and orientation.
        preset: target radar preset (range grid, azimuth count, sweep period).
        start_time_us: timestamp of the first azimuth, microseconds.

    Raises:
        ScanFormatError: not a 2-D array, fewer than ``MIN_SCAN_SIDE`` or more than ``MAX_SCAN_SIDE`` azimuths or
        range bins, power outside [0, 1].

    Returns:
        RadarScan with ``preset.num_azimuths`` rows and ``preset.num_range_bins`` bins, ready for
        ``write_navtech_png``.
    """
    p = get_preset(preset)
    array = np.asarray(array)
    if array.ndim != 2 or min(array.shape) < 2:
        raise ScanFormatError(f"a polar scan must be a 2-D array, got shape {array.shape}")
    power = _to_unit_power(array if layout.azimuth_axis == 0 else array.T)
    n_az_src, n_bins_src = power.shape
    check_scan_sides(n_az_src, n_bins_src, "the scan")
    # 2. range: sample each beam at the preset's bin centres (vectorised over azimuths).
    r_dst = p.range_offset_m + np.arange(p.num_range_bins) * p.range_resolution_m
    x = (r_dst - layout.range_offset_m) / layout.range_resolution_m
    inside = (x >= 0) & (x <= n_bins_src - 1)
    if int(inside.sum()) < MIN_SCAN_SIDE:  # (nearly) every output bin would be 0: a wrong offset or resolution
        src_lo = layout.range_offset_m
        src_hi = layout.range_offset_m + (n_bins_src - 1) * layout.range_resolution_m
        raise ScanFormatError(f"the scan's ranges {src_lo:g}..{src_hi:g} m (offset + bins x resolution) overlap "
                              f"fewer than {MIN_SCAN_SIDE} range bins of the {r_dst[0]:g}..{r_dst[-1]:g} m of preset "
                              f"{p.name!r}: check --range-offset and --range-resolution")
    i0 = np.clip(np.floor(x).astype(np.int64), 0, n_bins_src - 1)
    i1 = np.minimum(i0 + 1, n_bins_src - 1)
    w = (x - i0).astype(np.float32)
    resampled = power[:, i0] * (1 - w) + power[:, i1] * w
    resampled[:, ~inside] = 0.0
    # 3. azimuth: circular linear interpolation to the preset's count.
    if n_az_src != p.num_azimuths:
        a = np.arange(p.num_azimuths) * (n_az_src / p.num_azimuths)
        j0 = np.floor(a).astype(np.int64) % n_az_src
        j1 = (j0 + 1) % n_az_src
        wa = (a - np.floor(a)).astype(np.float32)[:, None]
        resampled = resampled[j0] * (1 - wa) + resampled[j1] * wa
    scan = RadarScan.from_power(np.clip(resampled, 0.0, 1.0).astype(np.float32), p, start_time_us)
    return replace(scan, azimuths=np.mod(scan.azimuths + layout.start_azimuth_rad, 2 * np.pi))
