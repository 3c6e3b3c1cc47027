"""Regenerate the simulator realism report: statistics table + images for docs/SIMULATOR.md.

Usage:
    python scripts/sim_report.py --real ../shared/data/real-oxford [--out docs/img] [--table report.md]

Renders (cached) the ``calib-oxford`` suite, compares its four weather conditions with the real Oxford scans
(``reradar sim-report`` prints the same table), and writes:
    sim_real_vs_sim.png   real (left) vs simulated clear (right), Cartesian +-80 m and polar 0-80 m
    sim_conditions.png    the same place under clear / rain / snow_cover / falling_snow (Cartesian)
    sim_polar.png, sim_cart.png   one simulated scan, polar and Cartesian
    sim_offroad.png       an off-road (OORD-like) scan
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from reradar_core.geometry.cartesian import CartesianConfig, polar_to_cartesian
from reradar_core.io.datasets import load_sequence
from reradar_core.sim.report import collect_scans, compare_table, folder_statistics
from reradar_core.sim.sensor import render_scan, scan_seed
from reradar_core.sim.suites import build_suite
from reradar_core.sim.trajectories import drive_route, synthetic_loop_route
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--real", type=Path, required=True)
    ap.add_argument("--out", type=Path, default=Path("docs/img"))
    ap.add_argument("--table", type=Path, default=None)
    ap.add_argument("--sim-index", type=int, default=8, help="which simulated clear scan to show (a straight street)")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    suite = build_suite("calib-oxford")
    folders = [suite.database[0], *suite.queries]
    cols = {"real Oxford": folder_statistics(args.real)}
    for f in folders:
        cols[f"sim {f.name}"] = folder_statistics(f)
    table = compare_table(cols)
    print(table)
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
