"""Tracking from an explicit prior whose heading is off: how many tracked answers are right, off or wrong?

For every revisit query of a two-traversal suite (a map keyframe within 20 m), the prior is the true mid-sweep
position with the heading turned by +-delta (sign seeded), position sigma 1 m, and a heading sigma of
delta / 1.5 (the truth within 1.5 sigma), 180 degrees ("heading unknown") or 2 degrees (a confident prior,
wrong by delta). ``Localizer.track`` then either
tracks (``mode`` tracking: judged against the truth, ok <= 2 m / 2 deg, off <= 20 m / 10 deg, else wrong) or
localizes globally (``TrackingConfig.covers``, or a refused registration).

    python benchmarks/tracking_heading_prior.py .cache/reradar/sim/v10/loop-sim --model our-3-loop-w05 --every 2

Prints one JSON row per (delta, sigma) pair. Used for ``TrackingConfig.max_start_yaw_rad`` (docs/BENCHMARKS.md,
"Session 22").
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("suite_dir", help="a rendered two-traversal suite folder holding lap1 and laps2-3")
    ap.add_argument("--model", default="our-3-loop-w05")
    ap.add_argument("--every", type=int, default=2, help="every n-th query scan")
    ap.add_argument("--database", default="lap1")
    ap.add_argument("--queries", default="laps2-3")
    ap.add_argument("--deltas", default="0,5,10,15,20,30,45,90,180", help="heading offsets, degrees")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    import torch

    from reradar_core.evaluation import localization_errors
    from reradar_core.io.datasets import load_sequence
    from reradar_core.localization import InMemoryKeyframes, LocalizationConfig, Localizer, PosePrior
    from reradar_core.model import DescriptorExtractor
    from reradar_core.retrieval import GlobalIndex

    torch.set_num_threads(1)
    ext = DescriptorExtractor.from_pretrained(args.model)
    db = load_sequence(f"{args.suite_dir}/{args.database}")
    q = load_sequence(f"{args.suite_dir}/{args.queries}")
    t0 = time.time()
    db_feats = [ext.describe(db.load_scan(i)) for i in range(len(db))]
    db_poses = db.mid_sweep_poses()
    qi = np.arange(0, len(q), args.every)
    q_feats = [ext.describe(q.load_scan(int(i))) for i in qi]
    q_poses = q.mid_sweep_poses()[qi]
    print(json.dumps({"features_s": round(time.time() - t0, 1), "keyframes": len(db_feats), "queries": len(q_feats)}))
    loc = Localizer(GlobalIndex(np.stack([f.global_descriptor for f in db_feats]).astype(np.float32)),
                    InMemoryKeyframes(db_feats, db_poses), LocalizationConfig())
    nearest = np.min(np.hypot(q_poses[:, None, 0] - db_poses[None, :, 0], q_poses[:, None, 1] - db_poses[None, :, 1]),
                     axis=1)
    revisit = nearest <= 20.0
    rng = np.random.default_rng(args.seed)
    for delta in (float(d) for d in args.deltas.split(",")):
        for sigma_kind in ("delta/1.5", "180", "2"):
            sigma = math.radians(float(sigma_kind) if sigma_kind in ("180", "2") else max(1.0, delta / 1.5))
            counts = {"tracked": 0, "tracked_ok": 0, "tracked_off": 0, "tracked_wrong": 0, "global_localized": 0}
            for f, gt, is_revisit in zip(q_feats, q_poses, revisit, strict=True):
                if not is_revisit:
                    continue
                prior = gt.copy()
                prior[2] += math.radians(delta) * rng.choice([-1, 1])
                res = loc.track(f, PosePrior(prior, 1.0, sigma))
                if res.mode == "tracking":
                    counts["tracked"] += 1
                    e_t, e_r = localization_errors(res.T_map_query[None], gt[None])
                    kind = "ok" if e_t[0] <= 2 and e_r[0] <= 2 else ("off" if e_t[0] <= 20 and e_r[0] <= 10 else "wrong")
                    counts[f"tracked_{kind}"] += 1
                elif res.localized:
                    counts["global_localized"] += 1
            print(json.dumps({"delta_deg": delta, "sigma_yaw_deg": sigma_kind, "revisits": int(revisit.sum()),
                              **counts}), flush=True)


if __name__ == "__main__":
    main()
