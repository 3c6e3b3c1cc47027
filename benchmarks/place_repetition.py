"""Choose the repeated-place bar (``LocalizationConfig.max_place_repetition``) on training data, and print its table.

Two measurements per target training split (``confidence_fit.SPLIT_MODELS``, each with its target-adapted model), none
on a benchmark query sequence:

1. **Maps.** Every keyframe's repetition (``Localizer.place_repetition``, shipped settings) on the split's pairing map
   (the benchmark database drive the split pairs with, ``training.suites.TRAINING_SPLITS``; an ordinary world) and on
   the map drive of its periodic world (``train-target-X-periodic``, ``sim.suites.periodic_suite``), each with every
   scan as a keyframe and with keyframes 12 m apart (``--map-spacings-m``; ``reradar build-map --min-spacing-m``):
   how many keyframes each bar marks.
2. **Runs.** Each map's unseen sessions localized on it with the shipped settings but the rule off (``reradar
   fit-confidence`` collects its own runs with the rule off too, ``confidence_fit.collection_config``): on a pairing map the split's ``confidence`` sessions, on a periodic map its world's
   ``confidence`` sessions. Per run the winning keyframe, whether it is ``localized`` and whether within the success
   thresholds (suite radius, 10 deg). A bar refuses an answer whose winner's repetition reaches it. The last 15 % of
   each session is held out (``confidence_fit`` split).

Rule (the tie margin's, ``confidence_fit.choose_place_margin``): of ``--grid``, the bars that refuse at most 0.5 % of
the correct answers of the ordinary worlds' runs (all maps and spacings pooled, outside the held-out tails;
``MAX_MARGIN_REFUSED_FRACTION``); of those, the largest that leaves the fewest wrong answers among the periodic worlds'
runs outside the held-out tails. Keyframes marked per map are reported too.

    python benchmarks/place_repetition.py [--splits train-target-loop,...] [--out /tmp/rep.json]

About 15 minutes on two cores with the renders and features cached (``reradar sim-suite``; features are computed
and cached on first use). Session 27's output chose 0.95 (docs/MODEL.md "Repeated places").
"""

from __future__ import annotations

import argparse
import itertools
import json
from dataclasses import replace
from pathlib import Path

import numpy as np

GRID = (0.70, 0.75, 0.80, 0.85, 0.90, 0.95, 1.00, 1.05, 1.10)
HOLDOUT = 0.15


def _counts(answered: np.ndarray, correct: np.ndarray, held: np.ndarray) -> dict[str, int]:
    """Wrong and correct ``localized`` answers among ``answered`` runs, outside and inside the held-out tails."""
    return {"fit_wrong": int((answered & ~correct & ~held).sum()), "fit_correct": int((answered & correct & ~held).sum()),
            "heldout_wrong": int((answered & ~correct & held).sum()),
            "heldout_correct": int((answered & correct & held).sum())}


def main() -> None:
    from tqdm import tqdm

    from reradar_core.baselines.ours import Ours, prepared_to_features
    from reradar_core.benchmark.runner import BenchConfig, prepare_sequence
    from reradar_core.evaluation.metrics import has_revisit, localization_errors, localization_success
    from reradar_core.localization.confidence_fit import MAX_MARGIN_REFUSED_FRACTION, SPLIT_MODELS, _localizer
    from reradar_core.localization.keyframes import select_keyframes
    from reradar_core.localization.pipeline import LocalizationConfig
    from reradar_core.sim.suites import build_suite
    from reradar_core.training.suites import TRAINING_SPLITS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--splits", default=",".join(SPLIT_MODELS), help="comma-separated target training splits")
    ap.add_argument("--grid", default=",".join(f"{g:g}" for g in GRID), help="comma-separated bars to compare")
    ap.add_argument("--map-spacings-m", default="0,12",
                    help="comma-separated keyframe spacings of the maps (select_keyframes, as build-map --min-spacing-m; "
                         "0 = every scan of the drive)")
    ap.add_argument("--out", type=Path, default=None, help="write the table as JSON here too")
    args = ap.parse_args()
    grid = sorted(float(g) for g in args.grid.split(","))
    spacings = [float(v) for v in args.map_spacings_m.split(",")]
    # the rule off: every run's winner, the rule applied afterwards through its keyframe's repetition
    config = replace(LocalizationConfig(), max_place_repetition=None)

    maps: dict[str, dict] = {}
    runs: dict[str, dict] = {}
    for split in args.splits.split(","):
        method = Ours(SPLIT_MODELS[split], localization=config)
        pairing = TRAINING_SPLITS[split]
        assert pairing is not None
        radius = build_suite(pairing, progress=False).radius_m
        for (suite_name, periodic), spacing in itertools.product(((pairing, False), (f"{split}-periodic", True)),
                                                                  spacings):
            name = suite_name if spacing <= 0 else f"{suite_name}@{spacing:g}m"
            suite = build_suite(suite_name, progress=True)
            bc = BenchConfig(radius_m=radius, rotation_stress=False, progress=True)
            db_seq = suite.load(suite.database[0])
            db = prepare_sequence([method], db_seq, bc)[method.name]
            all_poses = db_seq.mid_sweep_poses()
            keep = select_keyframes(all_poses, spacing)
            poses = all_poses[keep]
            loc = _localizer(method, [db.records[int(i)] for i in keep], poses, config)
            ratio = np.array([loc.place_repetition(k).ratio
                              for k in tqdm(range(len(loc)), desc=f"{name}: keyframe repetition", leave=False)])
            maps[name] = {"split": split, "periodic": periodic, "spacing_m": spacing, "keyframes": len(ratio),
                          "max_ratio": round(float(ratio.max()), 3),
                          "marked": {f"{g:g}": int((ratio >= g).sum()) for g in grid}}
            print(json.dumps({"map": name, **maps[name]}), flush=True)
            # the unseen sessions: the split's own on its pairing map, the periodic world's on that world's map
            sessions = suite if periodic else build_suite(split, progress=True)
            rows = []
            for qpath in sessions.confidence:
                qseq = sessions.load(qpath)
                q = prepare_sequence([method], qseq, bc)[method.name]
                gt = qseq.mid_sweep_poses()
                revisit = has_revisit(gt, poses, radius)
                n = len(q.records)
                for i in tqdm(range(n), desc=f"{name}/{qseq.name}", leave=False):
                    res = loc.localize(prepared_to_features(q.records[i]))
                    ok = False
                    if res.localized:
                        e_t, e_r = localization_errors(np.asarray(res.T_map_query)[None], gt[i][None])
                        ok = bool(localization_success(e_t, e_r, radius)[0]) and bool(revisit[i])
                    rep = ratio[res.best.keyframe_id] if res.best is not None else 0.0
                    rows.append((res.localized, ok, i >= (1.0 - HOLDOUT) * n, rep))
            a = np.array(rows, dtype=np.float64).reshape(-1, 4)
            localized, correct, held, rep = a[:, 0] > 0, a[:, 1] > 0, a[:, 2] > 0, a[:, 3]
            runs[name] = {"periodic": periodic, "runs": len(a), "rule_off": _counts(localized, correct, held),
                          "bars": {f"{g:g}": _counts(localized & (rep < g), correct, held) for g in grid}}
            print(json.dumps({"runs": name, **runs[name]}), flush=True)

    keys = ("fit_wrong", "fit_correct", "heldout_wrong", "heldout_correct")

    def total(periodic: bool, bar: str | None) -> dict[str, int]:
        return {k: sum((r["bars"][bar] if bar else r["rule_off"])[k] for r in runs.values()
                       if r["periodic"] == periodic) for k in keys}

    ordinary_off = total(False, None)
    allowed = [g for g in grid if ordinary_off["fit_correct"] - total(False, f"{g:g}")["fit_correct"]
               <= MAX_MARGIN_REFUSED_FRACTION * ordinary_off["fit_correct"]]
    chosen = None
    if allowed:
        fewest = min(total(True, f"{g:g}")["fit_wrong"] for g in allowed)
        chosen = max(g for g in allowed if total(True, f"{g:g}")["fit_wrong"] == fewest)
    print("\n| bar | ordinary maps: keyframes marked | ordinary worlds' unseen sessions: correct (refused) / wrong "
          "| periodic maps: marked | periodic fit runs: wrong / correct | periodic held out: wrong / correct |"
          "\n|---|---|---|---|---|---|")
    po, oo = total(True, None), ordinary_off
    print(f"| off | 0 | {oo['fit_correct']} (0) / {oo['fit_wrong']} | 0 | {po['fit_wrong']} / {po['fit_correct']} | "
          f"{po['heldout_wrong']} / {po['heldout_correct']} |")
    for g in grid:
        key = f"{g:g}"
        om = ", ".join(f"{m['marked'][key]} of {m['keyframes']}" for m in maps.values() if not m["periodic"])
        pm = ", ".join(f"{m['marked'][key]} of {m['keyframes']}" for m in maps.values() if m["periodic"])
        o, t = total(False, key), total(True, key)
        mark = " (chosen)" if g == chosen else "" if g in allowed else " (over budget)"
        print(f"| {key}{mark} | {om} | {o['fit_correct']} ({oo['fit_correct'] - o['fit_correct']}) / {o['fit_wrong']} | "
              f"{pm} | {t['fit_wrong']} / {t['fit_correct']} | {t['heldout_wrong']} / {t['heldout_correct']} |")
    print(f"\nchosen max_place_repetition: {chosen}")
    if args.out is not None:
        args.out.write_text(json.dumps({"maps": maps, "runs": runs, "allowed": allowed, "chosen": chosen}, indent=1))


if __name__ == "__main__":
    main()
