#!/usr/bin/env python
"""Check the scan loader and the Cen 2018 detector on real Oxford Radar RobotCar scans.

Usage:
    python scripts/check_real_oxford.py /work/shared/data/real-oxford/radar

Reads every ``<timestamp>.png`` in DIR (never copies them) and prints, per scan: the azimuth timestamps'
span (ms), the mean azimuth step (deg), the valid azimuth count, mean and 99th-percentile power, the Cen 2018
keypoint count with default parameters (z_q = 3, sigma = 17 bins, min range 58 bins) and the detection time;
then the mean keypoint count. The data's README quotes ~1,500-1,700 keypoints per scan from a reference
implementation.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from reradar_core.errors import ReRadarError
from reradar_core.io.presets import get_preset
from reradar_core.io.scan import read_navtech_png
from reradar_core.landmarks import Cen2018Config, detect_landmarks


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("directory", type=Path, help="folder holding the Navtech <timestamp>.png scans")
    parser.add_argument("--preset", default="oxford", help="radar preset (default: oxford)")
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
