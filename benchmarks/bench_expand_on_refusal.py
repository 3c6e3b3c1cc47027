"""Paired timing of the localize stage with and without ``LocalizationConfig.expand_on_refusal``.

Every query of one benchmark sequence is localized twice in one process, with and without the deeper search
on refusal, in alternating order (so load changes hit both alike), over the suite's database as the benchmark
builds it (cached features, the service's ``Localizer``). Prints mean / p50 / p90 / p99 and the ratios, with
the load average.

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_expand_on_refusal.py --suite boreas-sim \\
        --model our-3-boreas --query snow_cover
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from reradar_core.baselines.ours import Ours, prepared_to_features  # noqa: E402
from reradar_core.benchmark.runner import BenchConfig, prepare_sequence  # noqa: E402
from reradar_core.localization.pipeline import LocalizationConfig  # noqa: E402
from reradar_core.sim.suites import build_suite  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--suite", default="boreas-sim")
    ap.add_argument("--model", default="our-3-boreas")
    ap.add_argument("--query", default="", help="substring of the query sequence's name (default: the first)")
    ap.add_argument("--warmup", type=int, default=30, help="queries run first to fill the keyframe cache")
    args = ap.parse_args()
    bench = build_suite(args.suite, progress=False)
    on = LocalizationConfig()
    off = replace(on, expand_on_refusal=False)
    method = Ours(args.model, localization=on)
    bc = BenchConfig(radius_m=bench.radius_m, rotation_stress=False, progress=False)
    db_seq = bench.load(bench.database[0])
    db = prepare_sequence([method], db_seq, bc)[method.name]
    index = method.build_index([method.describe_prepared(r) for r in db.records])
    loc = method.localizer(index, db.records, db_seq.mid_sweep_poses())  # the benchmark's own Localizer
    matching = [p for p in bench.queries if args.query in str(p)]
    if not matching:
        ap.error(f"no query sequence of {args.suite} matches {args.query!r}; its query sequences: "
                 + ", ".join(Path(p).name for p in bench.queries))
    qpath = matching[0]
    q = prepare_sequence([method], bench.load(qpath), bc)[method.name]
    feats = [prepared_to_features(r) for r in q.records]
    for f in feats[: args.warmup]:
        loc.localize(f, on)
    times: dict[str, list[float]] = {"on": [], "off": []}
    localized = {"on": 0, "off": 0}
    deep: list[bool] = []  # with the rule: more than ``top_k`` candidates screened (either expansion)
    load0 = os.getloadavg()[0]
    for k, f in enumerate(feats):
        for name, cfg in ((("on", on), ("off", off)) if k % 2 == 0 else (("off", off), ("on", on))):
            t0 = time.perf_counter()
            result = loc.localize(f, cfg)
            times[name].append((time.perf_counter() - t0) * 1e3)
            localized[name] += result.localized
            if name == "on":
                deep.append(sum(c.screen_score is not None for c in result.candidates) > on.top_k)
    stats = {}
    for name, v in times.items():
        a = np.asarray(v)
        stats[name] = (a.mean(), *np.percentile(a, [50, 90, 99]))
        print(f"{name:>3}: n {len(a)}  mean {stats[name][0]:.1f}  p50 {stats[name][1]:.1f}  p90 {stats[name][2]:.1f}"
              f"  p99 {stats[name][3]:.1f} ms  localized {localized[name]}")
    on_ms, wide = np.asarray(times["on"]), np.asarray(deep)
    print(f"with the rule, {int(wide.sum())} of {len(wide)} queries screen more than top_k = {on.top_k} candidates: "
          f"mean {on_ms[wide].mean() if wide.any() else 0.0:.1f} ms, "
          f"{on_ms[wide].sum() / max(on_ms.sum(), 1e-9):.0%} of the localize time")
    ratios = [a / b for a, b in zip(stats["on"], stats["off"], strict=True)]
    print("on/off: mean {:.3f}  p50 {:.3f}  p90 {:.3f}  p99 {:.3f}".format(*ratios),
          f"(load average {load0:.1f} -> {os.getloadavg()[0]:.1f})")


if __name__ == "__main__":
    main()
