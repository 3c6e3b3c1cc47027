"""Simulator rendering speed: ms per scan for consecutive scans along a drive (target <= 200 ms per
400 x 3,768 Oxford-preset scan on the 2-core reference machine).

Usage:
    python benchmarks/bench_sim.py [--preset oxford] [--scans 60] [--profile urban] [--condition clear]
        [--trajectory FILE]      # default: a synthetic looped city route (no external data needed)

Prints a Markdown line for docs/BENCHMARKS.md. Render = world query + ray casting + sensor model;
write = PNG encoding + disk write of the Navtech PNG. Columns: render mean / median / p95, write mean,
total mean (wall ms), CPU ms per scan (render + write, less sensitive to other load), 1-min load average.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from reradar_core.io.datasets import write_sequence_scan
from reradar_core.io.presets import get_preset
from reradar_core.sim.sensor import render_scan, scan_seed
from reradar_core.sim.trajectories import drive_route, load_trajectory, scan_times, synthetic_loop_route
from reradar_core.sim.traversal import Traversal
from reradar_core.sim.world import RoadNetwork, World


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="oxford")
    ap.add_argument("--scans", type=int, default=60)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--profile", default="urban")
    ap.add_argument("--condition", default="clear")
    ap.add_argument("--trajectory", type=Path, default=None)
    ap.add_argument("--threads", type=int, default=1, help="OpenCV threads (the machine has 2 shared cores)")
    args = ap.parse_args()

    import cv2

    cv2.setNumThreads(args.threads)
    if args.trajectory is not None:
        traj = load_trajectory(args.trajectory)
        times = scan_times(traj)[200:]
    else:
        traj = drive_route(synthetic_loop_route(7, laps=1), seed=7)
        times = scan_times(traj, use_pose_times=False)
    world = World(RoadNetwork([traj.xy]), seed=1, profile=args.profile)
    trav = Traversal(world, seed=2, condition=args.condition)
    preset = get_preset(args.preset)
    render_ms, write_ms, cpu_ms = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.warmup + args.scans):
            c0 = time.process_time()
            t0 = time.perf_counter()
            scan = render_scan(trav, traj, int(times[k]), preset, scan_seed(2, k))
            t1 = time.perf_counter()
            write_sequence_scan(Path(tmp), preset.dataset_layout, scan)
            t2 = time.perf_counter()
            c2 = time.process_time()
            if k >= args.warmup:
                cpu_ms.append(1e3 * (c2 - c0))
                render_ms.append(1e3 * (t1 - t0))
                write_ms.append(1e3 * (t2 - t1))
    r, w = np.asarray(render_ms), np.asarray(write_ms)
    tot = r + w
    print(f"| {args.preset} {preset.num_azimuths}x{preset.num_range_bins} | {args.profile} / {args.condition} | "
          f"{args.scans} | {np.mean(r):.0f} | {np.median(r):.0f} | {np.percentile(r, 95):.0f} | {np.mean(w):.0f} | "
          f"{np.mean(tot):.0f} | {np.mean(cpu_ms):.0f} | {os.getloadavg()[0]:.1f} |")


if __name__ == "__main__":
    main()
