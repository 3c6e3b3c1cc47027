"""Pose-estimation accuracy of the localization verifiers on a simulated suite, given the right keyframe.

For each sampled query of the suite's first (or ``--query-index``) query sequence, the ground-truth-nearest
database keyframe is verified with each pose method (``guided``: descriptor-guided hypotheses scored by
landmark alignment; ``mutual_nn``: the paper's mutual nearest neighbours + RANSAC), and a random keyframe
more than 150 m away is verified too, to show how many inliers a wrong place collects. Prints success within
2 m / 2 deg, median errors, inlier percentiles and verification time.

    python benchmarks/bench_pose.py --suite boreas-sim --queries 30
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from reradar_core.geometry.se2 import angle_diff, relative_pose  # noqa: E402
from reradar_core.io.datasets import load_sequence  # noqa: E402
from reradar_core.localization.pipeline import Candidate, LocalizationConfig, verify_candidate  # noqa: E402
from reradar_core.model import DescriptorExtractor  # noqa: E402
from reradar_core.sim.suites import build_suite  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default="boreas-sim")
    ap.add_argument("--queries", type=int, default=30, help="queries sampled evenly along the sequence")
    ap.add_argument("--query-index", type=int, default=0, help="which query sequence of the suite")
    ap.add_argument("--model", default="default")
    ap.add_argument("--seed", type=int, default=0, help="seed for the wrong-place keyframe draw")
    args = ap.parse_args()
    torch.set_num_threads(1)
    suite = build_suite(args.suite, progress=False)
    db, q = load_sequence(suite.database[0]), load_sequence(suite.queries[args.query_index])
    ex = DescriptorExtractor.from_pretrained(args.model)
    db_poses = db.poses.poses
    cache: dict[int, object] = {}

    def keyframe(i: int):
        if i not in cache:
            cache[i] = ex.describe(db.load_scan(i))
        return cache[i]

    rng = np.random.default_rng(args.seed)
    picks = np.linspace(0, len(q) - 1, args.queries).round().astype(int)
    rows: dict[str, list[tuple[float, float, int, int, float]]] = {"guided": [], "mutual_nn": []}
    for j in picks:
        fq = ex.describe(q.load_scan(int(j)))
        T_w_q = q.poses.poses[j]
        dist = np.linalg.norm(db_poses[:, :2] - T_w_q[:2], axis=1)
        k = int(np.argmin(dist))
        far = np.flatnonzero(dist > 150.0)
        k_wrong = int(rng.choice(far)) if len(far) else None
        T_k_q = relative_pose(db_poses[k], T_w_q)
        for method in rows:
            cfg = LocalizationConfig(pose_method=method, min_inliers=2, min_inlier_ratio=0.0)
            t0 = time.perf_counter()
            v = verify_candidate(fq, Candidate(k, db_poses[k], keyframe(k), 0.0, 0), cfg)
            ms = (time.perf_counter() - t0) * 1e3
            if v.T_keyframe_query is None:
                e_t, e_r = np.inf, np.inf
            else:
                e_t = float(np.linalg.norm(v.T_keyframe_query[:2] - T_k_q[:2]))
                e_r = float(np.degrees(angle_diff(v.T_keyframe_query[2], T_k_q[2])))
            wrong = -1
            if k_wrong is not None:
                wrong = verify_candidate(fq, Candidate(k_wrong, db_poses[k_wrong], keyframe(k_wrong), 0.0, 0),
                                         cfg).num_inliers
            rows[method].append((e_t, e_r, v.num_inliers, wrong, ms))
    print(f"suite {args.suite}, query sequence {suite.queries[args.query_index].name}, {len(picks)} queries, "
          f"model {ex.model_id}")
    print("method     | success (<2 m, <2 deg) | median e_t (m) | median e_r (deg) | inliers right p5/p50 | "
          "inliers wrong p50/p95 | verify ms p50")
    for method, r in rows.items():
        a = np.array(r, dtype=np.float64)
        ok = (a[:, 0] < 2.0) & (a[:, 1] < 2.0)
        wrong = a[a[:, 3] >= 0, 3]
        print(f"{method:10s} | {ok.mean():22.0%} | {np.median(a[:, 0]):14.2f} | {np.median(a[:, 1]):16.2f} | "
              f"{np.percentile(a[:, 2], 5):8.0f} / {np.median(a[:, 2]):<9.0f} | "
              f"{np.median(wrong) if len(wrong) else float('nan'):8.0f} / "
              f"{np.percentile(wrong, 95) if len(wrong) else float('nan'):<10.0f} | {np.median(a[:, 4]):8.1f}")


if __name__ == "__main__":
    main()
