#!/usr/bin/env python3
"""How many retrieved candidates to screen and verify: Recall@1, SR, wrong poses and time per query for a grid
of (top_k, verify_k[, max_candidates]) and `localized` thresholds, ReRadar only, on a simulator suite.

    python benchmarks/bench_rerank.py --suite boreas-sim --model our-3-boreas --query-limit 130 \\
        --grid 5/5 10/2 20/3 40/3 20/3/60 --ratios 0.40 0.50

``max_candidates`` defaults to ``top_k`` here (no expansion); ``20/3/60`` is the service default (screen 20,
and up to 60 while no candidate aligns 60 % of the landmarks).

Features come from the benchmark's feature cache (computed once); verification runs for every setting.
Prints a Markdown table; times are per query (retrieval + screen + verification, not feature extraction) on
this machine, so compare them only within one run.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default="boreas-sim")
    ap.add_argument("--model", default="our-3-boreas")
    ap.add_argument("--query-limit", type=int, default=130, help="queries per query sequence (evenly spaced)")
    ap.add_argument("--grid", nargs="+", default=["5/5", "10/2", "20/3", "40/3", "20/3/60"],
                    help="top_k/verify_k[/max_candidates] settings")
    ap.add_argument("--ratios", nargs="+", type=float, default=[0.40, 0.50], help="min_inlier_ratio values")
    args = ap.parse_args()
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

    from reradar_core.baselines.ours import Ours
    from reradar_core.benchmark.runner import BenchConfig, evaluate_method, prepare_sequence
    from reradar_core.benchmark.suites import pairs_from_suite
    from reradar_core.localization import LocalizationConfig

    pairs, radius = pairs_from_suite(args.suite, query_limit=args.query_limit, progress=False)
    method = Ours(args.model, name=f"ours-{args.model}")
    cfg = BenchConfig(radius_m=radius, progress=False)
    print(f"suite {args.suite}, model {args.model}, radius {radius} m, {args.query_limit} queries per sequence\n")
    print("| sequence | top_k / verify_k / max_candidates | min inlier ratio | Recall@1 (%) | SR (%) | wrong poses (%) "
          "| ms/query |")
    print("|---|---|---|---|---|---|---|")
    for pair in pairs:
        db = prepare_sequence([method], pair.database, cfg)[method.name]
        q = prepare_sequence([method], pair.query, cfg)[method.name]
        db_poses = np.asarray(pair.database.poses.poses, np.float64)
        q_poses = np.asarray(pair.query.poses.poses, np.float64)
        for setting in args.grid:
            parts = [int(v) for v in setting.split("/")]
            top_k, verify_k = parts[0], parts[1]
            max_candidates = parts[2] if len(parts) > 2 else top_k
            for ratio in args.ratios:
                method.localization = LocalizationConfig(top_k=top_k, verify_k=verify_k, min_inlier_ratio=ratio,
                                                         max_candidates=max_candidates)
                run = evaluate_method(method, db, db_poses, q, q_poses, radius)
                s = run.summary
                print(f"| {pair.name} | {top_k} / {verify_k} / {max_candidates} | {ratio:.2f} | {s['recall@1']:.2f} | {s['sr']:.2f} | "
                      f"{s['wrong_pose_pct']:.2f} | {run.search_ms:.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
