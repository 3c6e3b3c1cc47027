"""What the localization stage's speed settings cost in accuracy, measured on a TRAINING split (never tune on the
benchmark's query sequences): every ``--every``-th scan of a query drive localized on a map of another drive of
the same route, with the default ``LocalizationConfig`` and with one setting lowered at a time; prints
localized / successful (20 m, 10 deg) / wrong answers and the localization stage's CPU time per query
(``time.thread_time``; features computed once beforehand).

    reradar build-map --dataset .cache/reradar/sim/v<SIM_VERSION>/train-target-boreas/2021-08-05-lane-2-falling_snow --out M
    python benchmarks/bench_speed_settings.py --map M \
        --queries .cache/reradar/sim/v<SIM_VERSION>/train-target-boreas/2021-08-05-lane2-snow_cover --every 4
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--map", type=Path, required=True)
    ap.add_argument("--queries", type=Path, required=True, help="query sequence folder (a training drive)")
    ap.add_argument("--every", type=int, default=4)
    args = ap.parse_args()

    import torch

    torch.set_num_threads(1)
    from maps.database import MapDatabase
    from maps.store import open_map
    from reradar_core.evaluation import localization_errors, localization_success, radius_for
    from reradar_core.io.datasets import load_sequence
    from reradar_core.localization import LocalizationConfig
    from reradar_core.localization.extractor import load_default_extractor

    seq = load_sequence(args.queries)
    idx = np.arange(0, len(seq), args.every)
    extractor = load_default_extractor()
    feats = [extractor.describe(seq.load_scan(int(i))) for i in idx]
    gts = seq.mid_sweep_poses()[idx]  # the answers are mid-sweep poses (docs/CONVENTIONS.md)
    radius_m = radius_for(seq.preset.name)
    kf_map = open_map(args.map)
    db = MapDatabase(kf_map, keyframe_cache_size=len(kf_map) + 1, preload=True)
    base = LocalizationConfig()
    settings = {
        "default": base,
        "refine_candidates=3": replace(base, alignment=replace(base.alignment, refine_candidates=3)),
        "refine_candidates=2": replace(base, alignment=replace(base.alignment, refine_candidates=2)),
        "num_hypotheses=2000": replace(base, alignment=replace(base.alignment, num_hypotheses=2000)),
        "screen_hypotheses=1000": replace(base, alignment=replace(base.alignment, screen_hypotheses=1000)),
    }
    for f in feats[:3]:  # warm-up
        db.localize(f)
    print(f"map {args.map.name} ({len(db)} keyframes), {len(feats)} queries of {seq.name}; "
          f"load average {os.getloadavg()[0]:.2f}")
    for name, cfg in settings.items():
        cpu, success, wrong, localized = [], 0, 0, 0
        for f, gt in zip(feats, gts, strict=True):
            t0 = time.thread_time()
            r = db.localize(f, cfg)
            cpu.append(time.thread_time() - t0)
            if not r.localized:
                continue
            localized += 1
            if localization_success(*localization_errors(r.T_map_query[None], gt[None]), radius_m)[0]:
                success += 1
            else:
                wrong += 1
        print(f"{name:24} localized {localized:4d}  success {success:4d}  wrong {wrong:3d}  "
              f"CPU per query mean {np.mean(cpu) * 1e3:6.1f} ms, p50 {np.median(cpu) * 1e3:6.1f} ms", flush=True)
    print(f"load average {os.getloadavg()[0]:.2f}")
    db.close()


if __name__ == "__main__":
    main()
