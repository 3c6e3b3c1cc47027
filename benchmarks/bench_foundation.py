#!/usr/bin/env python
"""Foundation stage timings: polar -> Cartesian, Cen 2018 landmarks, descriptor matching, RANSAC.

Usage:
    python benchmarks/bench_foundation.py                       # synthetic 400 x 3,768 Oxford-preset scan
    python benchmarks/bench_foundation.py --scan /work/shared/data/real-oxford/radar/1547131046353776.png

Prints the median, 90th percentile and minimum wall time over ``--repeats`` runs after warm-up, in
milliseconds, and the median process CPU time, with each stage's target (from the foundation issue) and
whether the median wall time meets it, plus the load average (the reference machine's 2 cores are shared
with other jobs; the minimum and the CPU time show the cost without contention).
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from reradar_core.geometry.cartesian import CartesianConfig, polar_to_cartesian
from reradar_core.geometry.se2 import transform_points
from reradar_core.io.scan import RadarScan, load_scan
from reradar_core.landmarks import detect_landmarks
from reradar_core.matching import RansacConfig, estimate_rigid_2d, match_descriptors

#: Speed goals from the foundation issue, ms (None: no target, reported for information).
TARGETS_MS: dict[str, float | None] = {
    "polar_to_cartesian 201px": None,
    "polar_to_cartesian 200px": None,
    "detect_landmarks": 15.0,
    "estimate_rigid_2d 1000 matches": 5.0,
    "match_descriptors 1000x1000x64": None,
}


def synthetic_oxford_scan(seed: int = 0) -> RadarScan:
    """A 400 x 3,768 Oxford-preset scan: gamma speckle correlated along range (sigma 2 bins, as real speckle
    is; i.i.d. noise would give ~10x the real keypoint count), a slow range fall-off, and 1,600 extended
    reflectors (2-30 bins, power +0.1..0.8). Gives ~1,550 Cen 2018 keypoints, like real Oxford scans."""
    rng = np.random.default_rng(seed)
    n_az, n_bins = 400, 3768
    power = rng.gamma(2.0, 0.02, size=(n_az, n_bins)).astype(np.float32)
    power = cv2.GaussianBlur(power, (0, 0), sigmaX=2.0, sigmaY=0.01)
    power += (0.05 * np.exp(-np.arange(n_bins) / 1500.0)).astype(np.float32)[None, :]
    n_targets = 1600
    rows = rng.integers(0, n_az, n_targets)
    bins = rng.integers(60, n_bins - 40, n_targets)
    lengths = rng.integers(2, 30, n_targets)
    strengths = rng.uniform(0.1, 0.8, n_targets).astype(np.float32)
    for r, b, n, s in zip(rows, bins, lengths, strengths, strict=True):
        power[r, b : b + n] += s
    return RadarScan.from_power(np.clip(power, 0.0, 1.0), "oxford", start_time_us=1_547_131_046_353_776)


def ransac_problem(seed: int = 0, n: int = 1000, n_inliers: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """1,000 putative matches, 300 consistent with a random rigid transform (0.3 m noise), 700 random."""
    rng = np.random.default_rng(seed)
    T = np.array([rng.uniform(-20, 20), rng.uniform(-20, 20), rng.uniform(-np.pi, np.pi)])
    src = rng.uniform(-64, 64, (n, 2))
    dst = transform_points(T, src) + rng.normal(0, 0.3, (n, 2))
    out = rng.permutation(n)[n_inliers:]
    dst[out] = rng.uniform(-64, 64, (len(out), 2))
    return src, dst


def time_it(fn: Callable[[], object], repeats: int, warmup: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """(wall ms, process CPU ms) per run. CPU time counts every thread of the process, so it is the work
    done, less sensitive than wall time to other processes sharing the cores."""
    for _ in range(warmup):
        fn()
    wall = np.empty(repeats)
    cpu = np.empty(repeats)
    for i in range(repeats):
        c0 = time.process_time()
        t0 = time.perf_counter()
        fn()
        wall[i] = time.perf_counter() - t0
        cpu[i] = time.process_time() - c0
    return wall * 1e3, cpu * 1e3


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Foundation stage timings (ms).")
    parser.add_argument("--scan", type=Path, default=None, help="a Navtech .png / polar .npy scan (default: synthetic)")
    parser.add_argument("--repeats", type=int, default=50, help="timed runs per stage (default 50)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the synthetic scan and RANSAC data")
    parser.add_argument("--cv-threads", type=int, default=None,
                        help="cv2.setNumThreads (default: OpenCV's; BLAS threads: set OPENBLAS_NUM_THREADS)")
    args = parser.parse_args(argv)
    if args.cv_threads is not None:
        cv2.setNumThreads(args.cv_threads)

    scan = load_scan(args.scan) if args.scan else synthetic_oxford_scan(args.seed)
    source = str(args.scan) if args.scan else f"synthetic Oxford-preset scan (seed {args.seed})"
    src, dst = ransac_problem(args.seed)
    rng = np.random.default_rng(args.seed)
    desc_a = rng.normal(size=(1000, 64)).astype(np.float16)
    desc_b = (desc_a.astype(np.float32) + 0.3 * rng.normal(size=(1000, 64))).astype(np.float16)

    n_kp = len(detect_landmarks(scan))
    est = estimate_rigid_2d(src, dst, RansacConfig(seed=args.seed))
    stages: dict[str, Callable[[], object]] = {
        "polar_to_cartesian 201px": lambda: polar_to_cartesian(scan, CartesianConfig()),
        "polar_to_cartesian 200px": lambda: polar_to_cartesian(scan, CartesianConfig.paper()),
        "detect_landmarks": lambda: detect_landmarks(scan),
        "estimate_rigid_2d 1000 matches": lambda: estimate_rigid_2d(src, dst, RansacConfig(seed=args.seed)),
        "match_descriptors 1000x1000x64": lambda: match_descriptors(desc_a, desc_b),
    }

    print(f"input: {source}: {scan.num_azimuths} x {scan.num_range_bins}, preset {scan.preset}, "
          f"{n_kp} Cen 2018 keypoints")
    print(f"RANSAC check: {est.num_inliers} inliers of 1000 (300 planted), {est.num_iterations} hypotheses")
    print(f"machine: {platform.processor() or platform.machine()}, python {platform.python_version()}, "
          f"numpy {np.__version__}, OpenCV threads {cv2.getNumThreads()}; median / p90 of {args.repeats} runs")
    if hasattr(os, "getloadavg"):
        print("load average at start: " + ", ".join(f"{v:.2f}" for v in os.getloadavg()))
    print(f"{'stage':<34}{'median ms':>10}{'p90 ms':>9}{'min ms':>9}{'cpu ms':>9}{'target ms':>11}  met (median)")
    for name, fn in stages.items():
        t, cpu = time_it(fn, args.repeats)
        target = TARGETS_MS[name]
        med = float(np.median(t))
        met = "-" if target is None else ("yes" if med <= target else "NO")
        tgt = "-" if target is None else f"{target:.1f}"
        print(f"{name:<34}{med:>10.2f}{np.percentile(t, 90):>9.2f}{t.min():>9.2f}{np.median(cpu):>9.2f}"
              f"{tgt:>11}  {met}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
