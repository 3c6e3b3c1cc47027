"""Open land on a calibration subset (issue 10, session 32; docs/SIMULATOR.md "Simulator v11"): the Recall@1 of
each baseline over all queries and split by whether the query stands in open land (``WorldProfile.open_share``),
with the share of queries in open land and in *deep* open land (open also at 16 points ``--deep-m`` around it).

Same subset and overrides as ``benchmarks/calibrate_sim.py`` (whose renders it uses, uncached):

    OPENBLAS_NUM_THREADS=1 python benchmarks/probe_open_land.py --suite offroad-sim-hard --label m23-o0.2 \\
        --set world.seed=23 --set route.seed=23 --set profile.offroad.open_share=0.2 \\
        --set profile.offroad.open_scale_m=600 --set profile.offroad.open_clutter_persistence=0

Each row is printed as JSON and appended to ``--json``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import calibrate_sim as C  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--suite", default="offroad-sim-hard")
    ap.add_argument("--window", default="0:1")
    ap.add_argument("--queries", type=int, default=2000)
    ap.add_argument("--revisit-m", type=float, default=25.0)
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="as calibrate_sim.py --set")
    ap.add_argument("--label", default="")
    ap.add_argument("--methods", default="ringkey,raplace,radvlad,referee")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--deep-m", type=float, default=80.0, help="radius of the deep-open test, metres")
    a = ap.parse_args(argv)
    ov = C.parse_overrides(a.overrides)
    w0, w1 = (float(x) for x in a.window.split(":"))
    t0 = time.perf_counter()
    data = C.render_subset(a.suite, (w0, w1), a.queries, None, ov, 1, False, False, a.revisit_m)
    world = C.subset_world(a.suite, ov)
    q = np.asarray(data["q_pose"])[:, :2]
    is_open = np.array([world.is_open_land(p) for p in q], dtype=bool)
    ring = a.deep_m * np.stack([np.cos(np.linspace(0, 2 * np.pi, 16, endpoint=False)),
                                np.sin(np.linspace(0, 2 * np.pi, 16, endpoint=False))], 1)
    deep = np.array([o and all(world.is_open_land(p + d) for d in ring) for o, p in zip(is_open, q, strict=True)])
    row: dict[str, object] = {"label": a.label, "suite": a.suite, "window": a.window, "overrides": ov,
                              "queries": int(len(q)), "open_pct": round(100 * is_open.mean(), 1),
                              "deep_open_pct": round(100 * deep.mean(), 1),
                              "render_s": round(time.perf_counter() - t0, 1), "load1": round(os.getloadavg()[0], 2)}
    for name in [s.strip() for s in a.methods.split(",") if s.strip()]:
        h = C.query_hits(name, data)
        row[name] = round(100 * h.mean(), 1)
        row[f"{name}_open"] = round(100 * h[is_open].mean(), 1) if is_open.any() else None
        row[f"{name}_closed"] = round(100 * h[~is_open].mean(), 1) if (~is_open).any() else None
    row["utc"] = time.strftime("%H:%M:%S", time.gmtime())
    C.emit_row(row, a.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
