"""Compare ``LocalizationConfig`` variants on the TRAINING splits (never a benchmark query sequence).

The pairing of ``reradar fit-confidence`` (``localization.confidence_fit.split_runs``): each split's sessions
(its training traversals and its ``confidence`` sessions) are localized on its benchmark domain's database
drive (the "full" map), and the queries without a map keyframe within the radius once more on the first half
of that drive (the "half" map, where most queries have no match). Every variant localizes every query in one
process, in alternating order (load changes hit all alike), at the shipped floor and bar. Prints, per split and
in total: correct / wrong ``localized`` answers (SR rule: within the suite's radius and 10 degrees), revisits
refused, answers that differ from the first variant, and the mean localize time per run.

    OPENBLAS_NUM_THREADS=1 python benchmarks/compare_settings_on_training_splits.py \\
        --splits train-target-loop,train-target-loop-open --step 2 \\
        --variant base= --variant "pre5=prescreen_keep=5"
    # the same with another model on every split (a cross-domain check): --model our-3-boreas
    # two models whose training traversals differ, on the sessions neither trained on: --sessions unseen --model PATH.pt

A variant is ``NAME=FIELD=VALUE[,FIELD=VALUE...]`` over ``LocalizationConfig``'s fields (int, float, none,
true / false; ``alignment.FIELD`` for the nested ``AlignmentConfig``); ``NAME=`` is the default config.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from reradar_core.baselines.ours import Ours  # noqa: E402
from reradar_core.evaluation.metrics import localization_errors, localization_success  # noqa: E402
from reradar_core.localization.confidence_fit import SPLIT_MODELS, split_runs  # noqa: E402
from reradar_core.localization.pipeline import LocalizationConfig  # noqa: E402


def _value(text: str) -> Any:
    low = text.strip().lower()
    if low == "none":
        return None
    if low in ("true", "false"):
        return low == "true"
    try:
        return int(text)
    except ValueError:
        return float(text)


def parse_variant(spec: str) -> tuple[str, LocalizationConfig]:
    """``NAME=FIELD=VALUE,...`` -> (name, config)."""
    name, _, body = spec.partition("=")
    config = LocalizationConfig()
    for item in filter(None, body.split(",")):
        key, _, val = item.partition("=")
        outer, _, inner = key.partition(".")  # ``alignment.screen_hypotheses``: a field of a nested config
        if outer not in {f.name for f in fields(config)}:
            raise SystemExit(f"unknown LocalizationConfig field {key!r} in variant {spec!r}")
        if inner:
            sub = getattr(config, outer)
            if inner not in {f.name for f in fields(sub)}:
                raise SystemExit(f"unknown field {key!r} in variant {spec!r}")
            config = replace(config, **{outer: replace(sub, **{inner: _value(val)})})
        else:
            config = replace(config, **{outer: _value(val)})
    return name, config


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--splits", default=",".join(SPLIT_MODELS))
    ap.add_argument("--step", type=int, default=2, help="every N-th query scan of each session")
    ap.add_argument("--model", default="", help="one model for every split (default: each split's own)")
    ap.add_argument("--sessions", choices=("all", "unseen", "training"), default="all",
                    help="unseen: only the splits' confidence sessions (no weight trained on them; compares models "
                         "whose training traversals differ); training: only the training traversals")
    ap.add_argument("--map-spacing-m", type=float, default=0.0,
                    help="map keyframes at least this far apart (metres), as `reradar build-map --min-spacing-m` "
                         "keeps them (0: every scan of the domain's database drive)")
    ap.add_argument("--variant", action="append", required=True)
    args = ap.parse_args()
    variants = dict(parse_variant(v) for v in args.variant)
    names = list(variants)
    totals = {n: np.zeros(5) for n in names}  # correct, wrong, refused revisits, differs, seconds
    runs_total = 0
    keep = {"all": (False, True), "unseen": (True,), "training": (False,)}[args.sessions]  # SplitRun.unseen values
    print(f"load average {os.getloadavg()[0]:.2f}", flush=True)
    for split in filter(None, args.splits.split(",")):
        method = Ours(args.model or SPLIT_MODELS[split], localization=variants[names[0]])
        radius, split_run_iter = split_runs(split, method, variants[names[0]], args.step, progress=False,
                                             map_spacing_m=args.map_spacing_m)
        per = {n: np.zeros(5) for n in names}
        runs = 0
        for k, run in enumerate(r for r in split_run_iter if r.unseen in keep):
            answers = {}
            for n in (names if k % 2 == 0 else names[::-1]):
                t0 = time.perf_counter()
                r = run.localizer.localize(run.features, variants[n])
                per[n][4] += time.perf_counter() - t0
                if r.localized:
                    e_t, e_r = localization_errors(np.asarray(r.T_map_query)[None], run.T_map_query[None])
                    ok = bool(localization_success(e_t, e_r, radius)[0]) and run.revisit
                    per[n][0 if ok else 1] += 1
                    answers[n] = (r.best.keyframe_id if r.best else -1, ok)
                else:
                    per[n][2] += run.revisit and run.map_name == "full"
                    answers[n] = None
            for n in names[1:]:
                per[n][3] += answers[n] != answers[names[0]]
            runs += 1
        runs_total += runs
        for n in names:
            totals[n] += per[n]
            c, w, rr, d, s = per[n]
            print(f"{split:24} {n:12} runs {runs:5d}  correct {int(c):5d}  wrong {int(w):3d}  revisits refused "
                  f"{int(rr):4d}  differ {int(d):3d}  localize {s / max(runs, 1) * 1e3:6.2f} ms/run", flush=True)
    for n in names:
        c, w, rr, d, s = totals[n]
        print(f"{'total':24} {n:12} runs {runs_total:5d}  correct {int(c):5d}  wrong {int(w):3d}  revisits refused "
              f"{int(rr):4d}  differ {int(d):3d}  localize {s / max(runs_total, 1) * 1e3:6.2f} ms/run")
    print(f"load average {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
