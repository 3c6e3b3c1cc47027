#!/usr/bin/env python
"""Recall@1 spread of the vocabulary baselines over k-means seeds (the reference code leaves the seed unset).

RadVLAD and ResNet18-NetVLAD fit their k-means words / NetVLAD centres on the database run; the OORD
reference (``sklearn.cluster.KMeans`` without ``random_state``) gives a different vocabulary on every run.
This script refits with each seed on a suite's (cached) prepared records and prints Recall@1 per seed and
the mean and standard deviation, so a single benchmark number can be read against that spread.

Usage:
    python benchmarks/bench_vocabulary_seeds.py --suite offroad-sim --query-limit 200 --method radvlad \
        --seeds 0 1 2 3 4 5 6 7 8 9
"""

from __future__ import annotations

import argparse
import os

import numpy as np

from reradar_core.baselines.radvlad import RadVLAD, RadVLADConfig
from reradar_core.baselines.resnet_netvlad import ResNetNetVLAD, ResNetNetVLADConfig
from reradar_core.benchmark.runner import BenchConfig, evaluate_method, prepare_sequence
from reradar_core.benchmark.suites import pairs_from_suite


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--suite", default="offroad-sim")
    ap.add_argument("--query-limit", type=int, default=None)
    ap.add_argument("--method", choices=("radvlad", "resnet18-netvlad"), default="radvlad")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(5)))
    args = ap.parse_args()

    pairs, radius = pairs_from_suite(args.suite, query_limit=args.query_limit, progress=False)
    cfg = BenchConfig(radius_m=radius, progress=False)
    for pair in pairs:
        recalls = []
        for seed in args.seeds:
            # only the k-means seed varies: prepared records (and the ResNet backbone) stay the same
            m = (RadVLAD(RadVLADConfig(seed=seed)) if args.method == "radvlad"
                 else ResNetNetVLAD(ResNetNetVLADConfig(kmeans_seed=seed)))
            db = prepare_sequence([m], pair.database, cfg)[m.name]
            q = prepare_sequence([m], pair.query, cfg)[m.name]
            run = evaluate_method(m, db, pair.database.poses.poses, q, pair.query.poses.poses, radius)
            recalls.append(float(run.summary["recall@1"]))
            print(f"{pair.name} {args.method} seed {seed}: Recall@1 {recalls[-1]:.2f} %", flush=True)
        r = np.array(recalls)
        print(f"{pair.name} {args.method}: mean {r.mean():.2f} %, std {r.std(ddof=1) if r.size > 1 else 0.0:.2f}, "
              f"min {r.min():.2f}, max {r.max():.2f} over {r.size} seeds "
              f"(load average {os.getloadavg()[0]:.1f})")


if __name__ == "__main__":
    main()
