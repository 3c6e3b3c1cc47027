"""How sure is the calibration table? Bootstrap intervals for the baselines' simulated Recall@1 and their order.

The calibration rule of issue 10 asks, per simulated sequence, for every hand-made baseline within ±10 points of its
published real-data Recall@1 and for the published order of the five. The simulated figures come from a few hundred
revisit queries (232-517), so some verdicts are decided by a query or two. From the per-query results that
``reradar bench`` writes (``<out>/per_query/<sequence>/<method>.npz``: ``correct``, ``positive``), this prints per
sequence:

- each baseline's Recall@1 over the revisit queries with its 95 % Wilson interval (the one ``reradar bench`` writes as
  ``recall@1_ci95``), the published value, and whether ±10 holds for the whole interval ("yes"), for none of it
  ("no") or for part of it ("undecided");
- every pair of baselines whose simulated order differs from the published one, the simulated difference with its
  95 % interval (paired bootstrap over the revisit queries, ``scipy.stats.bootstrap``, 2,000 resamples, seed 0) and
  the published difference: a swap whose interval contains 0 is within the simulator run's own noise (one whose
  interval ends exactly at 0 is called "at the edge"). The published values carry sampling noise of their own, not
  known here: the paper gives no intervals.

    python benchmarks/calibration_uncertainty.py .cache/reradar/bench/{loop-sim,loop-sim-hard,offroad-sim,\\
        offroad-sim-hard,boreas-sim}-v10-s15-baselines
"""

from __future__ import annotations

import argparse
import json
import sys
from itertools import combinations
from pathlib import Path

import numpy as np
from scipy.stats import bootstrap

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(Path(__file__).resolve().parent), str(ROOT)]

from calibrate_sim import PUBLISHED  # noqa: E402

from reradar_core.evaluation import proportion_interval  # noqa: E402

#: (suite, query sequence) -> the real sequence it stands for (docs/BENCHMARKS.md, calibration table)
STANDS_FOR = {
    ("loop-sim", "laps2-3"): "MulRan KAIST03",
    ("loop-sim-hard", "laps2-3-reverse"): "MulRan DCC01",
    ("offroad-sim", "day2-rain"): "OORD Hydro 1-vs-2",
    ("offroad-sim-hard", "day2-reverse"): "OORD Two Lochs 2-vs-1",
    ("boreas-sim", "2021-09-02-snow_cover"): "Boreas 2020-11-26",
    ("boreas-sim", "2021-09-02-falling_snow"): "Boreas 2021-01-26",
}
METHODS = ("raplace", "radvlad", "resnet18-netvlad", "referee", "ringkey")
HAND_MADE = ("raplace", "radvlad", "referee", "ringkey")  # ResNet18-NetVLAD* is exempt from +-10


def difference_interval(a: np.ndarray, b: np.ndarray, draws: int = 2000, seed: int = 0) -> tuple[float, float]:
    """95 % paired-bootstrap interval (percentile) of 100 (mean(a) - mean(b)); (Q,) bool hits of two methods."""
    res = bootstrap((a.astype(np.float64), b.astype(np.float64)),
                    lambda x, y, axis: 100.0 * (np.mean(x, axis=axis) - np.mean(y, axis=axis)), paired=True,
                    vectorized=True, n_resamples=draws, method="percentile", rng=np.random.default_rng(seed))
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def within_verdict(lo: float, hi: float, published: float, tol: float = 10.0) -> str:
    """'yes' if the whole interval lies within ``published`` ± ``tol``, 'no' if none of it, else 'undecided'."""
    if lo >= published - tol and hi <= published + tol:
        return "yes"
    if hi < published - tol or lo > published + tol:
        return "no"
    return "undecided"


def sequence_report(run: Path, seq: str, real: str, draws: int) -> list[str]:
    per = run / "per_query" / seq
    hits = {}
    for m in METHODS:
        z = np.load(per / f"{m}.npz")
        hits[m] = np.asarray(z["correct"])[np.asarray(z["positive"])]
    pub = PUBLISHED[real]
    lines = [f"#### {run.name} / {seq} (stands for {real}; {len(hits['ringkey'])} revisit queries)", "",
             "| method | simulated Recall@1 (95 % interval) | published | within ±10 |", "|---|---|---|---|"]
    for m in METHODS:
        r = 100.0 * hits[m].mean()
        lo, hi = (100.0 * v for v in proportion_interval(int(hits[m].sum()), len(hits[m])))
        verdict = within_verdict(lo, hi, pub[m]) if m in HAND_MADE else "exempt"
        lines.append(f"| {m} | {r:.2f} ({lo:.2f}–{hi:.2f}) | {pub[m]:.2f} | {verdict} |")
    swaps = []
    for a, b in combinations(METHODS, 2):
        published_diff = pub[a] - pub[b]
        d = 100.0 * (hits[a].mean() - hits[b].mean())
        if np.sign(d) == np.sign(published_diff):
            continue
        lo, hi = difference_interval(hits[a], hits[b], draws)
        if lo < 0.0 < hi:
            verdict = "within the run noise"
        elif lo == 0.0 or hi == 0.0:
            verdict = "at the edge of the run noise (interval ends at 0)"
        else:
            verdict = "significant"
        swaps.append(f"| {a} − {b} | {d:+.2f} ({lo:+.2f} to {hi:+.2f}) | {published_diff:+.2f} | {verdict} |")
    lines += ["", "| pair out of the published order | simulated difference (95 % interval) | published difference "
              "| swap |", "|---|---|---|---|"] + (swaps or ["| none | | | |"]) + [""]
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="reradar bench output folders (results.json, per_query/)")
    ap.add_argument("--draws", type=int, default=2000)
    a = ap.parse_args()
    out = []
    for run in a.runs:
        results = json.loads((run / "results.json").read_text())
        suite = results.get("suite")
        for seq in results["sequences"]:
            real = STANDS_FOR.get((suite, seq))
            if real is None:
                print(f"skipping {run.name}/{seq}: no published counterpart for suite {suite!r}", file=sys.stderr)
                continue
            out += sequence_report(run, seq, real, a.draws)
    print("\n".join(out))


if __name__ == "__main__":
    main()
