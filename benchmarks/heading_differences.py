"""Heading difference between a query pose and its nearest map pose: the real Boreas drives against the suites.

A realism check of the simulated drives (never of a benchmark's scans): on a revisit, how far does the vehicle
point from where it pointed on the map drive at the same place? Real drivers wander in their lane and the two
drives are matched at slightly different points of a curve; a reversed revisit is folded by 180 degrees.

- real: the two real Boreas pose files (``../shared/data/trajectories``), every moving pose of the second drive
  matched to the nearest pose of the first within 3 m, on all matches and on straights only (the first drive's
  heading changes by less than 1.5 degrees over 15 m either side);
- simulated: every suite's query poses matched to the nearest database pose within the suite's radius (the
  poses the benchmark evaluates), from the rendered pose files.

    python benchmarks/heading_differences.py ../shared/data/trajectories
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from reradar_core.geometry.se2 import wrap_angle  # noqa: E402
from reradar_core.io.datasets import load_sequence  # noqa: E402
from reradar_core.sim.suites import build_suite  # noqa: E402
from reradar_core.sim.trajectories import load_trajectory  # noqa: E402

SUITES = ("boreas-sim", "loop-sim", "loop-sim-hard", "offroad-sim", "offroad-sim-hard")


def folded_deg(dyaw: np.ndarray) -> np.ndarray:
    """|heading difference| in degrees, a reversal (|d| > 90 deg) folded by 180 deg."""
    a = np.abs(np.degrees(wrap_angle(dyaw)))
    return np.where(a > 90.0, 180.0 - a, a)


def row(label: str, a: np.ndarray) -> str:
    return (f"| {label} | {len(a)} | {np.median(a):.2f} | {np.percentile(a, 75):.2f} | {np.percentile(a, 90):.2f} "
            f"| {np.mean(a > 2) * 100:.1f} | {np.mean(a > 8) * 100:.1f} |")


def straight_mask(xy: np.ndarray, yaw: np.ndarray, half_m: float = 15.0, max_turn_deg: float = 1.5) -> np.ndarray:
    """(N,) bool: the drive's heading changes by less than ``max_turn_deg`` over ``half_m`` either side."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    lo = np.searchsorted(s, s - half_m)
    hi = np.minimum(np.searchsorted(s, s + half_m), len(s) - 1)
    turn = np.abs(np.degrees(wrap_angle(yaw[hi] - yaw[lo])))
    return (turn < max_turn_deg) & (s[hi] - s[lo] > 1.6 * half_m)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trajectories", help="folder with the two real Boreas *.radar_poses.csv files")
    args = ap.parse_args()

    print("| drives | matches | median | p75 | p90 | > 2 deg (%) | > 8 deg (%) |\n|---|---|---|---|---|---|---|")
    files = sorted(Path(args.trajectories).glob("*.csv"))
    a, b = load_trajectory(files[0]), load_trajectory(files[1])
    dist, j = cKDTree(a.xy).query(b.xy)
    moving = np.concatenate([[False], np.linalg.norm(np.diff(b.xy, axis=0), axis=1) > 0.3])
    ok = (dist < 3.0) & moving
    d = folded_deg(b.yaw - a.yaw[j])
    print(row("real Boreas, all matches", d[ok]))
    print(row("real Boreas, straights", d[ok & straight_mask(a.xy, a.yaw)[j]]))
    for name in SUITES:
        suite = build_suite(name)
        db = load_sequence(suite.database[0], layout=suite.layout).poses
        tree = cKDTree(db.xy)
        for qp in suite.queries:
            q = load_sequence(qp, layout=suite.layout).poses
            dist, j = tree.query(q.xy)
            ok = dist < suite.radius_m
            d = folded_deg(q.yaw - db.yaw[j])
            print(row(f"`{name}` / {qp.name}", d[ok]))
            print(row(f"`{name}` / {qp.name}, straights", d[ok & straight_mask(db.xy, db.yaw)[j]]))


if __name__ == "__main__":
    main()
