"""Named Navtech radar presets (range resolution, bin count, range offset, landmark minimum range).

Sources:
- Boreas CIR204-H: 0.0596 m/bin x 3,360 bins, -0.31 m range offset (pyboreas); sequences recorded after the
  sensor upgrade use 0.04381 m/bin (Burnett et al., IJRR 2023).
- Oxford Radar RobotCar / OORD CTS350-X: 0.0432 m/bin x 3,768 bins (Barnes et al., ICRA 2020; Gadd et al. 2024).
- MulRan CIR204: 0.0595 m/bin x 3,360 bins (Kim et al., ICRA 2020).
- Cen 2018 minimum range: 58 bins on Oxford-type scans, 42 on Boreas, as in the reference implementation
  (yeti/radar odometry code); MulRan shares the Boreas sensor family, so 42.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reradar_core.errors import ConfigError, shorten_echo

__all__ = ["PRESETS", "RadarPreset", "get_preset", "mid_sweep_times_us", "ENCODER_TICKS_PER_TURN"]

#: Navtech encoder counts per full turn: azimuth [rad] = encoder * pi / 2800.
ENCODER_TICKS_PER_TURN = 5600


@dataclass(frozen=True)
class RadarPreset:
    """Fixed properties of one radar sensor / dataset format.

    Attributes:
        name: preset name (``boreas``, ``boreas-2021``, ``oxford``, ``oord``, ``mulran``).
        range_resolution_m: metres per range bin.
        num_range_bins: range bins per azimuth (PNG columns after the 11 metadata columns).
        range_offset_m: added to ``bin * resolution`` to get the range of a bin centre, metres.
        num_azimuths: azimuths per sweep (400 on all Navtech datasets here).
        sweep_period_s: seconds per sweep (4 Hz).
        landmark_min_range_bins: Cen 2018 minimum range, in bins.
        dataset_layout: on-disk layout this preset belongs to (``boreas``, ``oxford``, ``mulran``).
    """

    name: str
    range_resolution_m: float
    num_range_bins: int
    range_offset_m: float = 0.0
    num_azimuths: int = 400
    sweep_period_s: float = 0.25
    landmark_min_range_bins: int = 58
    dataset_layout: str = "boreas"

    @property
    def max_range_m(self) -> float:
        """Range of the last bin centre, metres."""
        return self.range_offset_m + (self.num_range_bins - 1) * self.range_resolution_m


PRESETS: dict[str, RadarPreset] = {
    "boreas": RadarPreset("boreas", 0.0596, 3360, -0.31, landmark_min_range_bins=42, dataset_layout="boreas"),
    "boreas-2021": RadarPreset(
        "boreas-2021", 0.04381, 3360, -0.31, landmark_min_range_bins=42, dataset_layout="boreas"
    ),
    "oxford": RadarPreset("oxford", 0.0432, 3768, 0.0, landmark_min_range_bins=58, dataset_layout="oxford"),
    "oord": RadarPreset("oord", 0.0432, 3768, 0.0, landmark_min_range_bins=58, dataset_layout="oxford"),
    "mulran": RadarPreset("mulran", 0.0595, 3360, 0.0, landmark_min_range_bins=42, dataset_layout="mulran"),
}


def get_preset(name: str | RadarPreset) -> RadarPreset:
    """Return the preset called ``name`` (or ``name`` itself if already a preset).

    Raises:
        ConfigError: unknown preset name; the message lists the valid ones.
    """
    if isinstance(name, RadarPreset):
        return name
    try:
        return PRESETS[name.lower()]
    except KeyError:
        raise ConfigError(f"unknown radar preset {shorten_echo(name)!r}; choose one of {sorted(PRESETS)}") from None


def mid_sweep_times_us(first_azimuth_us: np.ndarray | int, preset: RadarPreset) -> np.ndarray:
    """The mean azimuth time of each sweep: ``first + (A - 1) / 2 * sweep_period / A``, int64 microseconds.

    A rigid registration of two whole sweeps aligns the sensor poses at (about) this time: the sensor moves
    while the antenna turns, and every azimuth is seen from the pose at its own time. Keyframe poses, pose
    answers and pose ground truth refer to it (docs/CONVENTIONS.md).

    Args:
        first_azimuth_us: scan timestamps (the first azimuth's time), microseconds, any shape.
        preset: the radar (``num_azimuths``, ``sweep_period_s``).
    """
    half = round(preset.sweep_period_s * 1e6 * (preset.num_azimuths - 1) / (2 * preset.num_azimuths))
    return np.asarray(first_azimuth_us, dtype=np.int64) + np.int64(half)
