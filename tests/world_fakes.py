"""A fake model that sees a fixed world, shared by the map-build and service tests of the pose-clock check."""

from __future__ import annotations

import numpy as np

from reradar_core.features import ScanFeatures
from reradar_core.geometry.cartesian import CartesianConfig
from reradar_core.io.scan import RadarScan


class WorldExtractor:
    """Fake model that sees a fixed world: each scan's landmarks are the world's points within 60 m of where the
    drive was at the scan's time (``truth``: time -> T_world_sensor), in the sensor frame, each with its own local
    descriptor, so that consecutive keyframes register (the real ``estimate_pose_guided``) as real scans would."""

    model_id = "world"
    weights_sha256 = "w" * 64
    descriptor_dim = 8
    local_dim = 16
    cartesian = CartesianConfig()

    def __init__(self, truth: dict[int, np.ndarray], seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        self.truth = truth
        self.points = rng.uniform(-250.0, 250.0, (3000, 2))
        desc = rng.normal(size=(3000, 16))
        self.desc = (desc / np.linalg.norm(desc, axis=1, keepdims=True)).astype(np.float32)

    def describe(self, scan: RadarScan) -> ScanFeatures:
        return self.describe_batch([scan])[0]

    def describe_batch(self, scans: list[RadarScan]) -> list[ScanFeatures]:
        out = []
        for scan in scans:
            x, y, yaw = self.truth[scan.timestamp_us]
            c, s = np.cos(yaw), np.sin(yaw)
            local = (self.points - [x, y]) @ np.array([[c, -s], [s, c]])  # R(yaw)^T (p - t)
            near = np.hypot(local[:, 0], local[:, 1]) < 60.0
            g = np.ones(self.descriptor_dim) / np.sqrt(self.descriptor_dim)
            out.append(ScanFeatures(g, local[near], self.desc[near], scan.timestamp_us))
        return out


def turning_drive(n: int = 160) -> tuple[np.ndarray, np.ndarray]:
    """Times (µs, 4 Hz) and true poses (N, 3) of a 10 m/s drive with three turns at irregular times."""
    t = np.arange(n) * 0.25
    yaw = sum(np.radians(a) * np.clip((t - t0) / d, 0.0, 1.0) for t0, a, d in [(8.0, 90.0, 3.0), (19.0, -60.0, 4.0),
                                                                               (31.0, 120.0, 5.0)])
    x = np.cumsum(10.0 * np.cos(yaw)) * 0.25
    y = np.cumsum(10.0 * np.sin(yaw)) * 0.25
    return 1_600_000_000_000_000 + (t * 1e6).astype(np.int64), np.column_stack([x, y, yaw])
