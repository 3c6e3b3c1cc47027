"""Tracking through a partly changed scene: does a session keep answering `localized` when the scene no longer
matches the map?

Renders (``reradar sim``, boreas preset, ``urban`` world seed 5) a 120 x 80 m rounded-rectangle loop driven at
8 m/s: the map drive (every 2nd scan, 91 keyframes) and four query drives of 182 scans (``DRIVES``): in the map's
world the same way round and the other way round, in a partly changed world (the world is generated from the set
of road polylines: the map's holds the loop both ways round, this one only the loop started half way) and in a
world of another seed along the same roads. Then replays the query
drives through ``Localizer.track`` with the ground-truth motion plus seeded noise as odometry
(``bench_service.bench_localizer``, the benchmark's own replay) and prints, per drive and seed, the scans
tracked and the localized answers outside 2 m / 2 degrees (the pose a vehicle can use) and outside 20 m / 10
degrees (wrong), and the same for global localization of every scan. The drives and worlds of the QA of session 23
(issue 11: "never a confident wrong pose"; its trajectory files, byte for byte).

    python benchmarks/tracking_changed_scene.py --work /tmp/tcs [--noise 0.05] [--seeds 0,1,2]

Rendering and the map take ~3 minutes on two cores the first time (kept in ``--work``).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np

#: the ``reradar`` command of this interpreter's environment
RERADAR = [sys.executable, "-c", "from reradar_cli.main import main; main()"]
#: loop width, height and corner radius (m), speed (m/s), pose spacing (m)
LOOP_W_M, LOOP_H_M, CORNER_R_M, SPEED_MPS, STEP_M = 120.0, 80.0, 20.0, 8.0, 0.5


def loop_poses(start_fraction: float = 0.0, reverse: bool = False) -> np.ndarray:
    """(N, 3) x m, y m, yaw rad every ``STEP_M`` along the rounded rectangle, anticlockwise from (0, 0) heading +x
    (clockwise when ``reverse``), starting ``start_fraction`` of the way round."""
    ds = 0.05
    pieces = [("s", LOOP_W_M - 2 * CORNER_R_M), ("a", math.pi / 2), ("s", LOOP_H_M - 2 * CORNER_R_M),
              ("a", math.pi / 2)] * 2
    out, xy, yaw = [], np.zeros(2), 0.0
    for kind, val in pieces:
        n = int(round((val if kind == "s" else CORNER_R_M * val) / ds))
        dth = 0.0 if kind == "s" else val / n
        for _ in range(n):
            out.append((xy[0], xy[1], yaw))
            xy = xy + ds * np.array([math.cos(yaw + dth / 2), math.sin(yaw + dth / 2)])
            yaw += dth
    dense = np.array(out)
    if reverse:
        dense = dense[::-1].copy()
        dense[:, 2] += math.pi
    k = int(start_fraction * len(dense))
    dense = np.concatenate([dense[k:], dense[:k]])
    return dense[:: int(round(STEP_M / ds))]


def write_trajectory(path: Path, poses: np.ndarray, t_s: np.ndarray | None = None) -> None:
    """A ``t_s,x,y,yaw_rad`` CSV: the (N,) times ``t_s`` (s), or poses ``STEP_M`` apart at ``SPEED_MPS``."""
    t = np.arange(len(poses)) * STEP_M / SPEED_MPS if t_s is None else np.asarray(t_s, np.float64)
    yaw = (poses[:, 2] + math.pi) % (2 * math.pi) - math.pi
    rows = [f"{ti:.6f},{x:.4f},{y:.4f},{a:.6f}" for ti, x, y, a in zip(t, poses[:, 0], poses[:, 1], yaw, strict=True)]
    path.write_text("t_s,x,y,yaw_rad\n" + "\n".join(rows) + "\n")


#: query drives: trajectory, the extra roads of its world, lateral offset (m), traversal seed, world seed. The world
#: is generated from its seed and its set of road polylines (``reradar sim --road``): the map's is seed 5, {map, rev}
DRIVES = {
    # the map's world, 1 m to the side
    "same-scene": ("map", ["rev"], -1.0, 31, 5),
    # the map's world, the other way round 1 m to the side
    "reversed": ("rev", ["map"], 1.0, 21, 5),
    # the same loop started half way, without the reversed polyline: part of the scene differs from the map's
    "changed-scene": ("half", [], -1.0, 31, 5),
    # the map's roads in a world of another seed (other buildings, trees, parked cars along the same road
    # geometry): an unmapped place of the map's shape, where every localized answer is wrong
    "other-world": ("map", ["rev"], -1.0, 31, 7),
}


def render(work: Path) -> tuple[Path, list[Path]]:
    """The map drive and the query drives (kept when already rendered); returns the map file and the query
    folders."""
    write_trajectory(work / "map.csv", loop_poses(0.0))
    write_trajectory(work / "half.csv", loop_poses(0.5))
    write_trajectory(work / "rev.csv", loop_poses(0.3, reverse=True))
    common = ["--preset", "boreas", "--profile", "urban"]
    runs = {"map": ["--trajectory", str(work / "map.csv"), "--road", str(work / "rev.csv"), "--every", "2",
                    "--seed", "5"]}
    for name, (traj, roads, lateral, seed, world) in DRIVES.items():
        runs[name] = ["--trajectory", str(work / f"{traj}.csv"), *(a for r in roads for a in ("--road",
                      str(work / f"{r}.csv"))), "--lateral", str(lateral), "--traversal-seed", str(seed),
                      "--seed", str(world)]
    for name, extra in runs.items():
        subprocess.run([*RERADAR, "sim", *extra, *common, "--out", str(work / name)], check=True)
    map_path = work / "map.h5"
    if not map_path.exists():
        subprocess.run([*RERADAR, "build-map", "--dataset", str(work / "map"), "--out", str(map_path)], check=True)
    return map_path, [work / name for name in DRIVES]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="folder for the renders and the map (kept)")
    ap.add_argument("--noise", type=float, default=0.05, help="odometry noise, share of each step")
    ap.add_argument("--seeds", default="0,1,2")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_service import bench_localizer

    map_path, queries = render(args.work)
    for seed in (int(s) for s in args.seeds.split(",")):
        res = bench_localizer(map_path, queries, every=1, odometry_noise=args.noise, seed=seed)
        for q in queries:
            tr = res[q.name]["tracking"]
            print(json.dumps({"drive": q.name, "seed": seed, "noise": args.noise, "scans": res[q.name]["scans"],
                              "tracked": tr["tracked_scans"], "localized_outside_2m_2deg": tr["outside_2m_2deg"],
                              "of_them_tracked": tr["outside_2m_2deg_from_tracking"], "wrong": tr["wrong"],
                              "not_localized": tr["not_localized"], "success_rate": round(tr["success_rate"], 4),
                              "global_outside_2m_2deg": res[q.name]["global"]["outside_2m_2deg"],
                              "global_not_localized": res[q.name]["global"]["not_localized"]}), flush=True)


if __name__ == "__main__":
    main()
