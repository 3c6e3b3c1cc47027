"""Which query-side change moves which baseline: turn, or add a world-fixed sector of clutter to, the query scans.

Reads (or renders) the default calibration subset of a suite exactly as ``benchmarks/calibrate_sim.py`` does
(``--window``, ``--queries``, ``--revisit-m``; no simulator override) and re-runs the chosen baselines with every
query scan changed in one way at a time (docs/SIMULATOR.md, "Heading wander and a changing sector, probed"):

- ``--turn DEG,...``: every query scan turned by DEG degrees (its azimuths shifted, linear interpolation between
  neighbouring azimuths), i.e. the vehicle pointing DEG degrees off its heading with the scene unchanged. The
  reference RaPlace is not invariant to heading changes (its Radon angle axis is never shifted); the others are.
- ``--sector M:W:F,...``: diffuse clutter (exponential, mean M on the 0-255 scale) added at 20-150 m within a
  sector W degrees wide that is fixed in the world (bearings 0..W), on a share F of the query scans (a seeded
  draw): a part of the scene that looks different on the query day (e.g. open water calm on one day and
  wind-roughened on the other).

    OPENBLAS_NUM_THREADS=1 python benchmarks/probe_query_perturbations.py --suite loop-sim-hard --turn 0,2,4,8,15
    OPENBLAS_NUM_THREADS=1 python benchmarks/probe_query_perturbations.py --suite offroad-sim-hard --sector 10:90:1
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calibrate_sim import recall_at_1, render_subset  # noqa: E402

from reradar_core.benchmark.rotation import rotate_power  # noqa: E402
from reradar_core.io.presets import get_preset  # noqa: E402


def with_sector_clutter(q: np.ndarray, yaw: np.ndarray, bin_m: float, mean: float, width_deg: float,
                        share: float, seed: int = 0) -> np.ndarray:
    """(N, A, R) query powers (0-255) with exponential clutter of ``mean`` added at 20-150 m in the world-fixed
    sector of bearings [0, width_deg) on a seeded share of the scans; ``yaw`` (N,) radians, map frame."""
    rng = np.random.default_rng(seed)
    n, a, r = q.shape
    out = q.copy()
    az = np.arange(a) * 2.0 * np.pi / a
    rng_m = np.arange(r) * bin_m
    range_ok = (rng_m > 20.0) & (rng_m < 150.0)
    for i in range(n):
        if rng.random() >= share:
            continue
        bearing = (az + yaw[i]) % (2.0 * np.pi)
        cells = (bearing < np.radians(width_deg))[:, None] & range_ok[None, :]
        out[i][cells] += rng.exponential(mean, int(cells.sum()))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", required=True)
    ap.add_argument("--window", default="0:0.5")
    ap.add_argument("--queries", type=int, default=80)
    ap.add_argument("--revisit-m", type=float, default=16.0)
    ap.add_argument("--methods", default="ringkey,raplace,radvlad,referee")
    ap.add_argument("--turn", default="", help="comma-separated turns in degrees")
    ap.add_argument("--sector", default="", help="comma-separated MEAN:WIDTH_DEG:SHARE triples")
    args = ap.parse_args()

    a, b = (float(v) for v in args.window.split(":"))
    data = render_subset(args.suite, (a, b), args.queries, None, {}, revisit_m=args.revisit_m)
    q = np.asarray(data["q_scans"]).astype(np.float32)
    yaw = np.asarray(data["q_pose"])[:, 2]
    bin_m = get_preset(str(data["preset"])).range_resolution_m
    methods = args.methods.split(",")
    t0 = time.perf_counter()

    def run(label: str, qq: np.ndarray) -> None:
        e = dict(data)
        e["q_scans"] = np.clip(np.round(qq), 0, 255).astype(np.uint8)
        figures = " / ".join(f"{recall_at_1(m, e):.1f}" for m in methods)
        print(f"| {args.suite} | {label} | {figures} |", flush=True)

    print(f"| suite | query change | {' / '.join(methods)} |\n|---|---|---|")
    for deg in (float(v) for v in args.turn.split(",") if v):
        run(f"turned {deg:g} deg", rotate_power(q, np.radians(deg)))
    for spec in (s for s in args.sector.split(",") if s):
        mean, width, share = (float(v) for v in spec.split(":"))
        run(f"sector clutter mean {mean:g}, {width:g} deg, share {share:g}",
            with_sector_clutter(q, yaw, bin_m, mean, width, share))
    print(f"load average {os.getloadavg()[0]:.2f}; {time.perf_counter() - t0:.0f} s; "
          f"{time.strftime('%H:%M:%S', time.gmtime())} UTC")


if __name__ == "__main__":
    main()
