"""Wrong poses and SR before / after the answer confidence, on a suite's query sequences (REPORTING ONLY).

One run of the benchmark's own runner (``run_benchmark``: same pairs, radius, code path and metrics as
``reradar bench``) with ReRadar deciding on the aligned-ratio floor alone (``min_confidence=0``, the decision
before the confidence) while every answer's confidence is recorded; the "with the bar" figures re-score the
same answers with those below the shipped model's bar rejected - exactly the pipeline's decision with the bar
(``guided``: localized = floor passed and confidence >= bar). Nothing here tunes anything: the bar was chosen
on training splits (``reradar fit-confidence``).

    python scripts/confidence_report.py --suite smoke
    python scripts/confidence_report.py --suite boreas-sim --model our-3-boreas --query-limit 260
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
KEYS = ("n_queries", "n_revisit", "n_no_match", "recall@1", "sr", "sr_all", "wrong_pose_pct",
        "wrong_pose_no_match_pct", "n_wrong_pose_revisit", "n_wrong_pose_no_match", "n_rejected_revisit",
        "e_t_m", "e_r_deg")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", required=True)
    ap.add_argument("--model", default="default")
    ap.add_argument("--query-limit", type=int, default=None, help="at most this many queries per sequence "
                    "(evenly spread, as `reradar bench --query-limit`)")
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT))  # this checkout's packages, not an installed copy
    from reradar_core.baselines.ours import Ours
    from reradar_core.benchmark.metrics import make_outcome, summarise
    from reradar_core.benchmark.runner import BenchConfig, run_benchmark
    from reradar_core.benchmark.suites import pairs_from_suite
    from reradar_core.localization import LocalizationConfig, default_confidence_model
    from reradar_core.paths import cache_dir

    class Recording(Ours):
        """ReRadar with the floor alone, recording each answer's confidence (in query order)."""

        def __init__(self, *a: Any, **k: Any) -> None:
            super().__init__(*a, **k)
            self.confidences: list[float] = []

        def localizer(self, index: Any, db_prepared: Any, db_poses: np.ndarray) -> Any:
            loc = super().localizer(index, db_prepared, db_poses)
            outer = self

            class Wrapped:
                def localize(self, features: Any, config: Any = None) -> Any:
                    res = loc.localize(features, config)
                    outer.confidences.append(float(res.confidence))
                    return res

            return Wrapped()

    pairs, radius = pairs_from_suite(args.suite, query_limit=args.query_limit)
    label = "ours" if args.model == "default" else f"ours-{args.model}"
    out = cache_dir("bench", f"confidence-{args.suite}")
    method = Recording(args.model, LocalizationConfig(min_confidence=0.0), name=f"{label}-floor")
    bar = default_confidence_model().min_confidence
    report: dict[str, Any] = {"suite": args.suite, "model": args.model, "radius_m": radius, "min_confidence": bar,
                              "query_limit": args.query_limit, "sequences": {}}
    for pair in pairs:  # one pair per run: the recorded confidences belong to that pair's queries
        method.confidences = []
        results = run_benchmark([pair], [method], out, BenchConfig(radius_m=radius, rotation_stress=False),
                                suite=args.suite)
        report.setdefault("load_average_1min_at_start", results["settings"]["load_average_1min_at_start"])
        floor = results["sequences"][pair.name][method.name]
        o = np.load(out / "per_query" / pair.name / f"{method.name}.npz")
        conf = np.asarray(method.confidences)
        assert len(conf) == len(o["retrieved"]), (len(conf), len(o["retrieved"]))
        est = np.array(o["est_pose"], dtype=np.float64)
        est[conf < bar] = np.nan  # the bar rejects these: no pose
        db_poses = pair.database.poses.poses
        outcome = make_outcome(o["retrieved"], o["distance"], est, pair.query.poses.poses, db_poses, radius, "pose")
        with_bar = summarise(outcome, pair.query.poses.poses, db_poses, radius, "pose")
        report["sequences"][pair.name] = {f"{label}-floor": {k: floor.get(k) for k in KEYS},
                                          label: {k: with_bar.get(k) for k in KEYS}}
    (out / "confidence_report.json").write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
