"""Tiny synthetic radar sequences for tests and quick harness checks (not for accuracy claims).

A world of point scatterers and wall segments; each scan puts every scatterer visible within range at its
(azimuth, range) cell with a short range/azimuth spread, plus speckle noise. Deterministic for a seed.
Sequences are written in the Boreas layout (``<seq>/radar/<t_us>.png`` + ``applanix/radar_poses.csv``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reradar_core.geometry.se2 import wrap_angle
from reradar_core.io.datasets import Sequence, load_sequence, write_sequence_poses, write_sequence_scan
from reradar_core.io.poses import PoseSequence
from reradar_core.io.presets import get_preset
from reradar_core.io.scan import RadarScan

__all__ = ["synthetic_world", "render_scan", "write_synthetic_sequence", "loop_poses"]


def synthetic_world(seed: int = 0, extent_m: float = 160.0, num_points: int = 500) -> np.ndarray:
    """(M, 3) scatterers (x [m], y [m], reflectivity in (0.3, 1]) in a square of side 2 * extent_m."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-extent_m, extent_m, size=(num_points, 2))
    # walls: dense lines of points, the structure place recognition keys on
    walls = []
    for _ in range(14):
        a = rng.uniform(-extent_m, extent_m, 2)
        d = rng.normal(size=2)
        d /= np.linalg.norm(d)
        t = np.arange(0.0, rng.uniform(15, 50), 1.0)
        walls.append(a[None] + t[:, None] * d[None])
    pts = np.vstack([pts] + walls)
    refl = rng.uniform(0.3, 1.0, size=(len(pts), 1))
    return np.hstack([pts, refl])


def render_scan(world: np.ndarray, T_world_sensor: np.ndarray, preset: str = "boreas", t_us: int = 0,
                noise_seed: int = 0, noise: float = 0.04, max_range_m: float = 120.0) -> RadarScan:
    """Render one polar scan of ``world`` from ``T_world_sensor`` (azimuth clockwise from +x)."""
    p = get_preset(preset)
    n_az, n_bins = p.num_azimuths, p.num_range_bins
    x, y, yaw = (float(v) for v in T_world_sensor)
    d = world[:, :2] - np.array([x, y])
    c, s = np.cos(yaw), np.sin(yaw)
    xs, ys = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]  # R(-yaw) d
    rng_m = np.hypot(xs, ys)
    keep = (rng_m > 3.0) & (rng_m < max_range_m)
    az = np.mod(np.arctan2(-ys[keep], xs[keep]), 2 * np.pi)
    ai = np.round(az / (2 * np.pi) * n_az).astype(np.int64) % n_az
    bi = np.round((rng_m[keep] - p.range_offset_m) / p.range_resolution_m).astype(np.int64)
    power = np.random.default_rng(noise_seed).random((n_az, n_bins)).astype(np.float32) * noise
    refl = world[keep, 2].astype(np.float32)
    for da, w_a in ((-1, 0.5), (0, 1.0), (1, 0.5)):
        for db in range(-6, 7):
            w = w_a * np.exp(-0.5 * (db / 3.0) ** 2)
            b = np.clip(bi + db, 0, n_bins - 1)
            np.maximum.at(power, ((ai + da) % n_az, b), (refl * w).astype(np.float32))
    scan = RadarScan.from_power(np.clip(power, 0, 1), p, start_time_us=t_us)
    return scan


def loop_poses(n: int, radius_m: float = 60.0, offset_m: tuple[float, float] = (0.0, 0.0),
               phase: float = 0.0, lateral_m: float = 0.0) -> np.ndarray:
    """(n, 3) poses around a circle (counter-clockwise, heading along the path)."""
    t = phase + np.linspace(0, 2 * np.pi, n, endpoint=False)
    r = radius_m + lateral_m
    xy = np.stack([offset_m[0] + r * np.cos(t), offset_m[1] + r * np.sin(t)], axis=1)
    yaw = wrap_angle(t + np.pi / 2)
    return np.hstack([xy, yaw[:, None]])


def write_synthetic_sequence(root: Path, world: np.ndarray, poses: np.ndarray, preset: str = "boreas",
                             t0_us: int = 1_600_000_000_000_000, seed: int = 0,
                             stamps_us: np.ndarray | None = None) -> Sequence:
    """Render ``poses`` and write them as a Boreas-layout sequence at ``root``; returns it loaded. Scan ``i`` is at
    ``stamps_us[i]`` (increasing µs), by default ``t0_us + i * 0.25 s`` (a jump between far-apart poses then needs
    its own time: the reader refuses a step faster than sound)."""
    root = Path(root)
    stamps = (t0_us + np.arange(len(poses), dtype=np.int64) * 250_000 if stamps_us is None
              else np.asarray(stamps_us, np.int64))
    for i, (pose, t) in enumerate(zip(poses, stamps, strict=True)):
        write_sequence_scan(root, "boreas", render_scan(world, pose, preset, int(t), noise_seed=seed * 100_003 + i))
    write_sequence_poses(root, "boreas", PoseSequence(stamps, poses[:, :2], poses[:, 2]))
    return load_sequence(root, "boreas", preset)
