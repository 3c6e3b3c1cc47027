"""Regenerate the simulator realism report: statistics table + images for docs/SIMULATOR.md.

Usage:
    python scripts/sim_report.py --real ../shared/data/real-oxford [--out docs/img] [--table report.md]

Renders (cached) the ``calib-oxford`` suite, compares its four weather conditions with the real Oxford scans
(``reradar sim-report`` prints the same table), and writes:
    sim_real_vs_sim.png   real (left) vs simulated clear (right), Cartesian +-80 m and polar 0-80 m
    sim_conditions.png    the same place under clear / rain / snow_cover / falling_snow (Cartesian)
    sim_polar.png, sim_cart.png   one simulated scan, polar and Cartesian
    sim_offroad.png       an off-road (OORD-like) scan

With ``--feature-check`` it also prints how camera keypoints (ORB, SIFT on the Cartesian image + RANSAC)
recover the motion between scans 1, 3, 5 and 10 frames apart, on the real scans (ground-truth odometry) and on
a simulated drive: a method that fails on real radar should fail here too.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from reradar_core.geometry.cartesian import CartesianConfig, pixel_to_metric, polar_to_cartesian
from reradar_core.geometry.se2 import relative_pose
from reradar_core.io.datasets import load_sequence
from reradar_core.matching import RansacConfig, estimate_rigid_2d
from reradar_core.sim.report import collect_scans, compare_table, folder_statistics
from reradar_core.sim.sensor import render_scan, scan_seed
from reradar_core.sim.suites import build_suite
from reradar_core.sim.trajectories import drive_route, scan_times, synthetic_loop_route
from reradar_core.sim.traversal import Traversal
from reradar_core.sim.world import RoadNetwork, World

GAIN = 2.0


def _cart(scan, half_m=80.0, px=641):
    img = polar_to_cartesian(scan, CartesianConfig(px, 2 * half_m / px))
    return np.clip(img * 255 * GAIN, 0, 255).astype(np.uint8)


def _polar(scan, max_m=80.0, size=(640, 400)):
    n = int(np.searchsorted(scan.ranges_m, max_m))
    img = np.clip(scan.power[:, :n] * 255 * GAIN, 0, 255).astype(np.uint8)
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA)


def _label(img, text):
    out = img.copy()
    cv2.putText(out, text, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, 255, 1, cv2.LINE_AA)
    return out


def _small(img, side=400):
    return cv2.resize(img, (side, side), interpolation=cv2.INTER_AREA)


def _write(path: Path, img) -> None:
    cv2.imwrite(str(path), img, [cv2.IMWRITE_PNG_COMPRESSION, 9])


def _feature_pose_errors(scans, poses, gaps, detector, norm) -> dict[int, tuple[float, float]]:
    """Per frame gap: (fraction of pairs with translation error < 1 m, median error m) for keypoint matching
    on 0.4 m/px Cartesian images + mutual matching + RANSAC (1 m threshold)."""
    cfg = CartesianConfig(401, 0.4)
    feats = []
    for s in scans:
        img = np.clip(polar_to_cartesian(s, cfg) * 255 * GAIN, 0, 255).astype(np.uint8)
        feats.append(detector.detectAndCompute(img, None))
    out = {}
    for g in gaps:
        errs = []
        for i in range(len(scans) - g):
            (ka, da), (kb, db) = feats[i + g], feats[i]
            err = np.inf
            if da is not None and db is not None and len(ka) >= 3 and len(kb) >= 3:
                m = cv2.BFMatcher(norm, crossCheck=True).match(da, db)
                pa = pixel_to_metric(np.array([[k.pt[1], k.pt[0]] for k in ka])[[x.queryIdx for x in m]], cfg)
                pb = pixel_to_metric(np.array([[k.pt[1], k.pt[0]] for k in kb])[[x.trainIdx for x in m]], cfg)
                est = estimate_rigid_2d(pa, pb, RansacConfig(inlier_threshold_m=1.0, seed=0))
                if est.success:
                    err = float(np.hypot(*(est.pose[:2] - relative_pose(poses[i], poses[i + g])[:2])))
            errs.append(err)
        e = np.asarray(errs)
        out[g] = (float(np.mean(e < 1.0)), float(np.median(e)))
    return out


def feature_check(real_dir: Path) -> str:
    real = load_sequence(real_dir)
    real_scans = [real.load_scan(i) for i in range(len(real))]
    traj = drive_route(synthetic_loop_route(7, laps=1), seed=7)
    world = World(RoadNetwork([traj.xy]), seed=7, profile="urban")
    trav = Traversal(world, 71)
    times = scan_times(traj, use_pose_times=False)[40:40 + len(real_scans)]
    sim_scans = [render_scan(trav, traj, int(t), "oxford", scan_seed(71, k)) for k, t in enumerate(times)]
    sim_poses = traj.interpolate(times)
    gaps = (1, 3, 5, 10)
    step_r = float(np.mean(np.linalg.norm(np.diff(real.poses.xy, axis=0), axis=1)))
    step_s = float(np.mean(np.linalg.norm(np.diff(sim_poses[:, :2], axis=0), axis=1)))
    lines = ["| detector | data (m per frame) | " + " | ".join(f"gap {g}" for g in gaps) + " |",
             "|---" * (len(gaps) + 2) + "|"]
    for name, det, norm in (("ORB", cv2.ORB_create(1000), cv2.NORM_HAMMING),
                            ("SIFT", cv2.SIFT_create(1000), cv2.NORM_L2)):
        for label, scans, poses, step in (("real Oxford", real_scans, real.poses.poses, step_r),
                                          ("sim clear", sim_scans, sim_poses, step_s)):
            res = _feature_pose_errors(scans, poses, gaps, det, norm)
            cells = [f"{100 * res[g][0]:.0f} % / {res[g][1]:.2f} m" for g in gaps]
            lines.append(f"| {name} | {label} ({step:.2f}) | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--real", type=Path, required=True)
    ap.add_argument("--out", type=Path, default=Path("docs/img"))
    ap.add_argument("--table", type=Path, default=None)
    ap.add_argument("--sim-index", type=int, default=8, help="which simulated clear scan to show (a straight street)")
    ap.add_argument("--feature-check", action="store_true", help="also run the ORB/SIFT check (see above)")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    suite = build_suite("calib-oxford")
    folders = [suite.database[0], *suite.queries]
    cols = {"real Oxford": folder_statistics(args.real)}
    for f in folders:
        cols[f"sim {f.name}"] = folder_statistics(f)
    table = compare_table(cols)
    print(table)
    if args.feature_check:
        fc = feature_check(args.real)
        print()
        print(fc)
        table = table + "\n\n" + fc
    if args.table:
        args.table.write_text(table + "\n")

    real = collect_scans(args.real, 11)[5]
    sim = load_sequence(folders[0]).load_scan(args.sim_index)
    top = np.hstack([_label(_small(_cart(real)), "real (Oxford)"), _label(_small(_cart(sim)), "simulated (clear)")])
    bot = np.hstack([_label(_polar(real, 80.0, (400, 250)), "real polar 0-80 m"),
                     _label(_polar(sim, 80.0, (400, 250)), "sim polar 0-80 m")])
    _write(args.out / "sim_real_vs_sim.png", np.vstack([top, bot]))
    _write(args.out / "sim_polar.png", _polar(sim, 165.0, (800, 400)))
    _write(args.out / "sim_cart.png", _cart(sim, 100.0, 601))

    # one place, four conditions (same world, same pose, one traversal per condition)
    traj = drive_route(synthetic_loop_route(7, laps=1), seed=7)
    world = World(RoadNetwork([traj.xy]), seed=7, profile="urban")
    t0 = int(traj.timestamps_us[0] + 40_000_000)
    tiles = []
    for k, cond in enumerate(("clear", "rain", "snow_cover", "falling_snow")):
        scan = render_scan(Traversal(world, 71 + k, cond), traj, t0, "oxford", scan_seed(71 + k, 0))
        tiles.append(_label(_small(_cart(scan)), cond))
    _write(args.out / "sim_conditions.png", np.vstack([np.hstack(tiles[:2]), np.hstack(tiles[2:])]))

    off = drive_route(synthetic_loop_route(21, laps=1, block_m=(250.0, 400.0), n_blocks=2), seed=21)
    ow = World(RoadNetwork([off.xy]), seed=21, profile="offroad")
    scan = render_scan(Traversal(ow, 211), off, int(off.timestamps_us[0] + 60_000_000), "oord", scan_seed(211, 0))
    _write(args.out / "sim_offroad.png",
           np.hstack([_label(_small(_cart(scan, 100.0)), "off-road (oord preset)"),
                      _label(_polar(scan, 100.0, (400, 400)), "polar 0-100 m")]))


if __name__ == "__main__":
    main()
