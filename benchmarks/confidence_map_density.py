"""How the answer confidence holds on sparser maps, and which agreement cue to fit (training splits only).

``reradar fit-confidence``'s pairing (``localization.confidence_fit``: each split's sessions on its domain's map
drive, plus the no-match queries on its first half) on maps with every scan as a keyframe and on maps whose
keyframes are ``--spacing-m`` apart (``select_keyframes``, as ``reradar build-map --min-spacing-m``). Every run
keeps the raw counts behind the agreement cue - how many of the top ``TOP_N`` other candidates lie within the
place radius of the answer (``agreeing``), how many others were looked at, how many map keyframes other than the
winner's lie within it - so that each definition of the cue can be fitted and judged on the same runs:

- ``shipped``: the shipped model and cues, not re-fitted (the agreement as a fraction of the top ``TOP_N``);
- ``fraction``: the same cue, re-fitted on both map densities;
- ``normalised``: agreeing / min(others looked at, map neighbours) (1 without neighbours), re-fitted;
- ``deficit``: (agreeing - that minimum) / ``TOP_N``, re-fitted.

Fits use ``confidence_fit.fit_from_data`` (floor and bar chosen on the fit runs, per-group wrong-answer rule with
each density a group of its own); the table reports the held-out tails (never fitted on), per map density.

    OPENBLAS_NUM_THREADS=1 python benchmarks/confidence_map_density.py --spacing-m 12 --runs runs.npz
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

from reradar_core.baselines.ours import Ours  # noqa: E402
from reradar_core.geometry.se2 import compose  # noqa: E402
from reradar_core.localization.confidence import CUE_NAMES, default_confidence_model  # noqa: E402
from reradar_core.localization.confidence_fit import (  # noqa: E402
    PLACE_RADIUS_M,
    PROBE_FLOOR,
    SPLIT_MODELS,
    TOP_N,
    FitData,
    fit_from_data,
    label_run,
    map_group,
    split_runs,
)
from reradar_core.localization.pipeline import LocalizationConfig  # noqa: E402

AGREE = CUE_NAMES.index("agreement")


def collect(spacings: list[float], step: int, holdout: float) -> dict[str, np.ndarray]:
    """One row per run: the shipped cues, the agreement's raw counts, the labels (``FitData``'s fields)."""
    cols: dict[str, list] = {k: [] for k in ("cues", "has_pose", "correct", "eligible", "revisit", "heldout",
                                            "split", "unseen", "agreeing", "looked_at", "neighbours")}
    config = replace(LocalizationConfig(), min_confidence=0.0, min_inlier_ratio=PROBE_FLOOR)
    for split, model in SPLIT_MODELS.items():
        method = Ours(model, localization=config)
        for spacing in spacings:
            t0 = time.time()
            radius, runs = split_runs(split, method, config, step, progress=False, map_spacing_m=spacing)
            n = 0
            for run in runs:
                res = run.localizer.localize(run.features, config)
                row = label_run(run, res, radius, holdout)  # the fit's own row (``collect_split``)
                agreeing = looked = near = 0
                if row[1]:  # a pose: the agreement's counts, and the map keyframes near the answer
                    best = res.best
                    T = np.asarray(compose(best.T_map_keyframe, best.T_keyframe_query))
                    looked = min(TOP_N, len(res.candidates) - 1)
                    agreeing = round(row[0][AGREE] * looked)
                    kf_xy = np.asarray(run.localizer.keyframes.poses, np.float64)[:, :2]
                    within = np.hypot(kf_xy[:, 0] - T[0], kf_xy[:, 1] - T[1]) <= PLACE_RADIUS_M
                    within[best.keyframe_id] = False
                    near = int(np.count_nonzero(within))
                for key, value in zip(("cues", "has_pose", "correct", "eligible", "revisit", "heldout", "unseen"),
                                      row, strict=True):
                    cols[key].append(value)
                cols["split"].append(map_group(split, spacing))
                cols["agreeing"].append(agreeing)
                cols["looked_at"].append(looked)
                cols["neighbours"].append(near)
                n += 1
            print(f"{map_group(split, spacing):30} {n:5d} runs  {time.time() - t0:5.0f} s  load "
                  f"{os.getloadavg()[0]:.2f}", flush=True)
    return {k: np.asarray(v) for k, v in cols.items()}


def agreement_variant(z: dict[str, np.ndarray], name: str) -> np.ndarray:
    """The cue matrix with the agreement column of definition ``name`` (module docstring)."""
    cues = np.array(z["cues"], np.float64)
    agreeing, looked, near = (z[k].astype(np.float64) for k in ("agreeing", "looked_at", "neighbours"))
    possible = np.minimum(looked, near)
    if name == "normalised":
        col = np.where(looked == 0, 0.0, np.where(possible > 0, np.minimum(agreeing, possible) / np.maximum(
            possible, 1), 1.0))
    elif name == "deficit":
        col = (np.minimum(agreeing, possible) - possible) / TOP_N
    else:
        return cues
    cues[:, AGREE] = np.where(z["has_pose"], col, 0.0)
    return cues


def data_with(z: dict[str, np.ndarray], cues: np.ndarray) -> FitData:
    return FitData(cues, z["has_pose"].astype(bool), z["correct"].astype(bool), z["eligible"].astype(bool),
                   z["revisit"].astype(bool), z["heldout"].astype(bool), z["split"].astype(str),
                   z["unseen"].astype(bool))


def judge(p: np.ndarray, d: FitData, floor: float, bar: float, rows: np.ndarray) -> tuple[int, int, int, int]:
    """(runs, correct localized, wrong localized, revisits refused) over ``rows``."""
    aligned = d.cues[:, CUE_NAMES.index("aligned_ratio")]
    acc = rows & d.eligible & d.has_pose & (aligned >= floor) & (p >= bar)
    return (int(rows.sum()), int((acc & d.correct).sum()), int((acc & ~d.correct).sum()),
            int((rows & d.revisit & ~acc).sum()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spacing-m", type=float, default=12.0, help="the sparser maps' keyframe spacing, metres")
    ap.add_argument("--step", type=int, default=1, help="every N-th query scan of each session")
    ap.add_argument("--holdout", type=float, default=0.15)
    ap.add_argument("--runs", default="", help="npz of the runs: read when it exists, else written")
    args = ap.parse_args()
    path = Path(args.runs) if args.runs else None
    if path is not None and path.is_file():
        z = dict(np.load(path, allow_pickle=False))
    else:
        z = collect([0.0, args.spacing_m], args.step, args.holdout)
        if path is not None:
            np.savez_compressed(path, **z)
    shipped = default_confidence_model()
    dense = ~np.char.endswith(z["split"].astype(str), "m")
    ho = z["heldout"].astype(bool)
    print(f"\nheld-out tails: runs / correct localized / wrong localized / revisits refused "
          f"(dense maps; {args.spacing_m:g} m maps)")
    for name in ("shipped", "fraction", "normalised", "deficit"):
        d = data_with(z, agreement_variant(z, name))
        if name == "shipped":
            model, floor, bar = shipped, shipped.min_aligned_ratio, shipped.min_confidence
        else:
            model, report = fit_from_data(d, meta={})
            floor, bar = report["min_aligned_ratio"], report["min_confidence"]
        p = np.where(d.has_pose, model.predict(d.cues), 0.0)
        out = [judge(p, d, floor, bar, ho & m) for m in (dense, ~dense)]
        coef = dict(zip(CUE_NAMES, np.round(model.coef, 2).tolist(), strict=True))
        print(f"{name:11} floor {floor:.2f} bar {bar:.3f}  " + "  |  ".join(
            f"{r} / {c} / {w} / {rr}" for r, c, w, rr in out) + f"  agreement weight {coef['agreement']:+.2f}")


if __name__ == "__main__":
    main()
