#!/usr/bin/env python
"""Check the scan loader and the Cen 2018 detector on real Oxford Radar RobotCar scans.

Usage:
    python scripts/check_real_oxford.py /work/shared/data/real-oxford/radar

Reads every ``<timestamp>.png`` in DIR (never copies them) and prints, per scan: the azimuth timestamps'
span (ms), the mean azimuth step (deg), the valid azimuth count, mean and 99th-percentile power, the Cen 2018
keypoint count with default parameters (z_q = 3, sigma = 17 bins, min range 58 bins) and the detection time;
then the mean keypoint count. The data's README quotes ~1,500-1,700 keypoints per scan from a reference
implementation.

With ``--odometry radar_odometry.csv`` (default: ``DIR/../radar_odometry.csv`` when present) it also checks
landmarks + matching + RANSAC against the ground-truth odometry on scan pairs 1, 3, 5 and 10 frames apart.
Local descriptors there are plain 13 x 13 Cartesian patches (0.25 m/px) around each keypoint, a stand-in
for the learned ones that only works for the small rotations between nearby scans. The Oxford odometry is
in the dataset's x-forward / y-right / yaw-clockwise frame; our sensor frame is y-left (docs/CONVENTIONS.md),
so the ground truth is compared as (x, -y, -yaw).
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

import numpy as np

from reradar_core.errors import ReRadarError
from reradar_core.geometry.cartesian import CartesianConfig, metric_to_pixel, polar_to_cartesian
from reradar_core.geometry.se2 import angle_diff, compose
from reradar_core.io.presets import get_preset
from reradar_core.io.scan import RadarScan, read_navtech_png
from reradar_core.landmarks import Cen2018Config, detect_landmarks
from reradar_core.matching import RansacConfig, estimate_rigid_2d, match_descriptors

_PATCH_CFG = CartesianConfig(width_px=1201, resolution_m=0.25)  # +-150 m
_PATCH_HALF = 6


def patch_features(scan: RadarScan) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints (K, 2) metres and (K, 169) mean-free Cartesian patch descriptors (no rotation invariance)."""
    lm = detect_landmarks(scan)
    img = np.pad(polar_to_cartesian(scan, _PATCH_CFG), _PATCH_HALF)
    rc = np.round(metric_to_pixel(lm.xy_m, _PATCH_CFG)).astype(int)
    inside = np.all((rc >= 0) & (rc < _PATCH_CFG.width_px), axis=1)
    rc = rc[inside] + _PATCH_HALF
    offs = np.arange(-_PATCH_HALF, _PATCH_HALF + 1)
    patches = img[rc[:, 0, None, None] + offs[None, :, None], rc[:, 1, None, None] + offs[None, None, :]]
    patches = patches.reshape(len(rc), -1)
    return lm.xy_m[inside], patches - patches.mean(axis=1, keepdims=True)


def read_oxford_odometry(path: Path) -> dict[tuple[int, int], np.ndarray]:
    """{(source_radar_ts, destination_radar_ts): T_dst_src in OUR frame (x fwd, y left, yaw ccw)}."""
    out: dict[tuple[int, int], np.ndarray] = {}
    with path.open(newline="") as fh:
        for row in csv.DictReader(fh):
            key = (int(row["source_radar_timestamp"]), int(row["destination_radar_timestamp"]))
            # Oxford's frame is y-right with clockwise yaw: flip y and yaw into ours.
            out[key] = np.array([float(row["x"]), -float(row["y"]), -float(row["yaw"])])
    return out


def odometry_check(files: list[Path], odometry: Path, preset: str) -> None:
    odo = read_oxford_odometry(odometry)
    stamps = [int(f.stem) for f in files]
    feats = [patch_features(read_navtech_png(f, preset)) for f in files]
    print(f"\npose check against {odometry} (T_earlier_later, ground truth in our y-left frame)")
    header = f"{'gap':>4}{'pair':>7}{'matches':>9}{'inliers':>9}{'est x,y m / yaw deg':>30}{'gt':>26}{'e_t m':>8}{'e_r deg':>9}"
    print(header)
    print("-" * len(header))
    for gap in (1, 3, 5, 10):
        errors = []
        for i in range(0, len(files) - gap, gap):
            T_gt = np.zeros(3)
            try:
                for j in range(i, i + gap):
                    T_gt = compose(T_gt, odo[(stamps[j + 1], stamps[j])])
            except KeyError as exc:
                print(f"{gap:>4}{i:>7}  no odometry row for {exc}")
                continue
            xy_src, d_src = feats[i + gap]
            xy_dst, d_dst = feats[i]
            m = match_descriptors(d_src, d_dst)
            est = estimate_rigid_2d(xy_src[m[:, 0]], xy_dst[m[:, 1]], RansacConfig())
            e_t = float(np.linalg.norm(est.pose[:2] - T_gt[:2]))
            e_r = float(np.degrees(angle_diff(est.pose[2], T_gt[2])))
            if est.success:
                errors.append((e_t, e_r))
            est_txt = f"{est.pose[0]:7.2f},{est.pose[1]:6.2f} / {np.degrees(est.pose[2]):6.2f}"
            gt_txt = f"{T_gt[0]:7.2f},{T_gt[1]:6.2f} / {np.degrees(T_gt[2]):6.2f}"
            print(f"{gap:>4}{i:>7}{len(m):>9}{est.num_inliers:>9}{est_txt:>30}{gt_txt:>26}{e_t:>8.2f}{e_r:>9.2f}"
                  + ("" if est.success else f"  FAILED: {est.reason}"))
        if errors:
            e = np.array(errors)
            print(f"     gap {gap}: {len(e)} pairs, median e_t {np.median(e[:, 0]):.2f} m, "
                  f"median e_r {np.median(e[:, 1]):.2f} deg")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("directory", type=Path, help="folder holding the Navtech <timestamp>.png scans")
    parser.add_argument("--preset", default="oxford", help="radar preset (default: oxford)")
    parser.add_argument("--odometry", type=Path, default=None,
                        help="Oxford radar_odometry.csv (default: DIR/../radar_odometry.csv if present)")
    args = parser.parse_args(argv)

    files = sorted(args.directory.glob("*.png"))
    if not files:
        print(f"error: no .png scans in {args.directory}", file=sys.stderr)
        return 2
    config = Cen2018Config()
    header = (f"{'scan':<22}{'span ms':>9}{'step deg':>10}{'valid':>7}{'mean pw':>9}{'p99 pw':>8}"
              f"{'keypoints':>11}{'ms':>7}")
    print(header)
    print("-" * len(header))
    counts = []
    for path in files:
        try:
            scan = read_navtech_png(path, args.preset)
        except ReRadarError as exc:
            print(f"{path.name:<22} unreadable: {exc}")
            continue
        span_ms = (scan.timestamps_us[-1] - scan.timestamps_us[0]) / 1e3
        step_deg = float(np.degrees(np.mean(np.diff(np.unwrap(scan.azimuths)))))
        detect_landmarks(scan, config)  # warm-up (workspace allocation)
        t0 = time.perf_counter()
        lm = detect_landmarks(scan, config)
        dt_ms = (time.perf_counter() - t0) * 1e3
        counts.append(len(lm))
        print(f"{path.name:<22}{span_ms:>9.1f}{step_deg:>10.4f}{int(scan.valid.sum()):>7}"
              f"{scan.power.mean():>9.4f}{np.percentile(scan.power, 99):>8.3f}{len(lm):>11}{dt_ms:>7.1f}")
    if not counts:
        return 1
    c = np.array(counts)
    min_range = get_preset(args.preset).landmark_min_range_bins
    print("-" * len(header))
    print(f"{len(c)} scans: keypoints mean {c.mean():.0f}, min {c.min()}, max {c.max()} "
          f"(z_q={config.z_q}, sigma={config.sigma_bins} bins, min range {min_range} bins)")
    odometry = args.odometry or args.directory.parent / "radar_odometry.csv"
    if odometry.is_file():
        odometry_check(files, odometry, args.preset)
    elif args.odometry:
        print(f"error: no odometry file {odometry}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
