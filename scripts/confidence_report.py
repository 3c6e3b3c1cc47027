"""Wrong poses and SR before / after the answer confidence, on a suite's query sequences (REPORTING ONLY).

Runs the benchmark's own runner (``run_benchmark``, same pairs, radius and code path as ``reradar bench``) with
two copies of ReRadar that differ only in the decision: ``<name>-floor`` answers ``localized`` on the
aligned-ratio floor alone (``min_confidence=0``, the decision before the confidence), ``<name>`` uses the shipped
confidence model and its bar. Nothing here tunes anything: the bar was chosen on training splits
(``reradar fit-confidence``).

    python scripts/confidence_report.py --suite smoke
    python scripts/confidence_report.py --suite boreas-sim --model our-3-boreas
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

KEYS = ("n_queries", "n_revisit", "n_no_match", "recall@1", "sr", "sr_all", "wrong_pose_pct",
        "wrong_pose_no_match_pct", "n_wrong_pose_revisit", "n_wrong_pose_no_match", "n_rejected_revisit",
        "e_t_m", "e_r_deg")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", required=True)
    ap.add_argument("--model", default="default")
    ap.add_argument("--query-limit", type=int, default=None)
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT))  # this checkout's packages, not an installed copy
    from reradar_core.baselines.ours import Ours
    from reradar_core.benchmark.runner import BenchConfig, run_benchmark
    from reradar_core.benchmark.suites import pairs_from_suite
    from reradar_core.localization import LocalizationConfig, default_confidence_model
    from reradar_core.paths import cache_dir

    pairs, radius = pairs_from_suite(args.suite, query_limit=args.query_limit)
    label = "ours" if args.model == "default" else f"ours-{args.model}"
    methods = [Ours(args.model, LocalizationConfig(min_confidence=0.0), name=f"{label}-floor"),
               Ours(args.model, name=label)]
    out = cache_dir("bench", f"confidence-{args.suite}")
    results = run_benchmark(pairs, methods, out, BenchConfig(radius_m=radius, rotation_stress=False),
                            suite=args.suite)
    model = default_confidence_model()
    report = {"suite": args.suite, "model": args.model, "radius_m": radius,
              "min_confidence": model.min_confidence,
              "load_average_1min_at_start": results["settings"]["load_average_1min_at_start"],
              "sequences": {seq: {m: {k: v.get(k) for k in KEYS} for m, v in per.items()}
                            for seq, per in results["sequences"].items()}}
    (out / "confidence_report.json").write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
