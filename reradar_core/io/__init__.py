"""Radar scan and pose I/O in the real dataset formats (Navtech PNG, .npy, Boreas/MulRan/plain pose CSVs)."""

from reradar_core.io.poses import (
    PoseSequence,
    read_boreas_radar_poses,
    read_mulran_global_pose,
    read_poses,
    read_txyyaw_csv,
    write_boreas_radar_poses,
    write_mulran_global_pose,
    write_txyyaw_csv,
)
from reradar_core.io.presets import PRESETS, RadarPreset, get_preset
from reradar_core.io.scan import (
    RadarScan,
    decode_navtech_png_bytes,
    encode_navtech_png_bytes,
    load_scan,
    load_scan_bytes,
    read_navtech_png,
    read_polar_npy,
    write_navtech_png,
)

__all__ = [
    "PRESETS",
    "PoseSequence",
    "RadarPreset",
    "RadarScan",
    "decode_navtech_png_bytes",
    "encode_navtech_png_bytes",
    "get_preset",
    "load_scan",
    "load_scan_bytes",
    "read_boreas_radar_poses",
    "read_mulran_global_pose",
    "read_navtech_png",
    "read_polar_npy",
    "read_poses",
    "read_txyyaw_csv",
    "write_boreas_radar_poses",
    "write_mulran_global_pose",
    "write_navtech_png",
    "write_txyyaw_csv",
]
