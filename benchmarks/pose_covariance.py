"""Fit the pose covariance's scales (``matching.uncertainty.PoseCovarianceConfig``) on training data, and print its table.

Data (never a benchmark query sequence): each target training split's sessions localized on its pairing map, the
benchmark database drive of its domain (``confidence_fit.split_runs``: the pairing ``reradar fit-confidence`` uses,
each split with its target-adapted model), with the shipped settings but the covariance's scales at 1 (the
registration's own sigma^2 H^-1). Kept: revisit queries answered ``localized`` within the success thresholds (suite
radius, 10 deg); a wrong answer is the confidence's business, not the covariance's. Per answer the error
(ground truth - estimate; x m, y m, yaw rad, map frame) and the covariance with scales 1 (the registration's own
sigma^2 H^-1 with the prior's information added; every model below scales only the registration's part, as the
library does). The last 15 % of each session is
held out (``confidence_fit``'s split).

Models, each fitted on the rows outside the held-out tails:

- ``shipped``: the registration part scaled by S = diag(sqrt(k_t), sqrt(k_t), sqrt(k_r)) (``scaled``), one (k_t, k_r)
  for motion-compensated answers and one for rigid ones (``PoseCovarianceConfig``), each chosen so that 95 % of those
  answers' position errors lie inside the 95 % ellipse (k_t) and 95 % of their heading errors inside the 95 %
  interval (k_r): what the API promises;
- ``scaled-ML``: one (k_t, k_r) for all answers by maximum likelihood (Gaussian errors: NEES 3 on the fit rows, but
  the errors' tails are heavier than a Gaussian's, so fewer than 95 % inside the 95 % ellipsoid);
- ``scaled+floor``: the scaled model + diag(a^2, a^2, b^2) by maximum likelihood: the registration's geometry plus an
  error every answer has;
- ``constant``: diag(a^2, a^2, b^2), the same for every answer (what a user without a covariance would assume);

reported per split (fit rows and held-out tails): the mean normalised squared error (NEES, 3 when calibrated),
the share of answers inside the 50 / 90 / 95 / 99 % ellipsoids (3-DoF, and position / heading alone), the
held-out negative log-likelihood per answer (lower = the model predicts the errors better), and the Spearman
correlation between the predicted and the actual error sizes.

    python benchmarks/pose_covariance.py [--splits train-target-loop,...] [--step 2] [--data /tmp/cov.npz] [--out cov.json]

About 10 minutes on two cores with the renders and features cached (``reradar sim-suite``; features are computed
and cached on first use). ``--data`` keeps the collected rows: a second run with the same file only fits.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import optimize, stats

HOLDOUT = 0.15


def collect(splits: list[str], step: int) -> dict[str, np.ndarray]:
    """Rows (``split``, ``heldout``, ``unseen``, ``compensated``, ``error`` (M, 3), ``cov0`` (M, 3, 3)) of the splits'
    right answers."""
    from reradar_core.baselines.ours import Ours
    from reradar_core.evaluation.metrics import localization_errors, localization_success, pose_error
    from reradar_core.localization.confidence_fit import SPLIT_MODELS, split_runs
    from reradar_core.localization.pipeline import LocalizationConfig
    from reradar_core.matching.uncertainty import PoseCovarianceConfig

    config = replace(LocalizationConfig(), covariance=PoseCovarianceConfig(
        position_scale=1.0, heading_scale=1.0, rigid_position_scale=1.0, rigid_heading_scale=1.0))
    rows: dict[str, list] = {"split": [], "heldout": [], "unseen": [], "compensated": [], "error": [], "cov0": []}
    for split in splits:
        method = Ours(SPLIT_MODELS[split], localization=config)
        radius, runs = split_runs(split, method, config, step, progress=True)
        for run in runs:
            if run.map_name != "full" or not run.revisit:
                continue
            res = run.localizer.localize(run.features, config)
            if not res.localized or res.T_map_query is None or res.pose_covariance is None:
                continue
            e_t, e_r = localization_errors(res.T_map_query[None], run.T_map_query[None])
            if not localization_success(e_t, e_r, radius)[0]:
                continue
            err = pose_error(run.T_map_query, res.T_map_query)
            rows["split"].append(split)
            rows["heldout"].append(run.index >= (1.0 - HOLDOUT) * run.session_size)
            rows["unseen"].append(run.unseen)
            rows["compensated"].append(res.motion_compensated)
            rows["error"].append(err)
            rows["cov0"].append(res.pose_covariance)
    return {"split": np.array(rows["split"], dtype=str), "heldout": np.array(rows["heldout"], bool),
            "unseen": np.array(rows["unseen"], bool), "compensated": np.array(rows["compensated"], bool),
            "error": np.array(rows["error"], np.float64).reshape(-1, 3),
            "cov0": np.array(rows["cov0"], np.float64).reshape(-1, 3, 3)}


def scaled(cov0: np.ndarray, k_t: float, k_r: float) -> np.ndarray:
    """(M, 3, 3) the covariance ``registration_covariance`` gives with scales (k_t, k_r), from the one it gave with
    scales 1 (``cov0``, which holds the prior): (S^-1 (cov0^-1 - P) S^-1 + P)^-1, S = diag(sqrt(k_t), sqrt(k_t),
    sqrt(k_r)), P the prior's information: only the registration's part is scaled, as in the library."""
    from reradar_core.matching.uncertainty import PoseCovarianceConfig

    p = PoseCovarianceConfig().prior_information  # the shipped prior, as the rows were collected with
    s_inv = 1.0 / np.sqrt(np.array([k_t, k_t, k_r]))
    registration = np.linalg.inv(cov0) - p
    return np.linalg.inv(registration * np.outer(s_inv, s_inv) + p)


def floored(cov0: np.ndarray, k_t: float, k_r: float, a_m: float, b_rad: float) -> np.ndarray:
    """(M, 3, 3) the scaled model (``scaled``) + diag(a^2, a^2, b^2)."""
    return scaled(cov0, k_t, k_r) + np.diag([a_m ** 2, a_m ** 2, b_rad ** 2])


def constant(n: int, a_m: float, b_rad: float) -> np.ndarray:
    """(n, 3, 3) diag(a^2, a^2, b^2)."""
    return np.broadcast_to(np.diag([a_m ** 2, a_m ** 2, b_rad ** 2]), (n, 3, 3)).copy()


def nll(error: np.ndarray, cov: np.ndarray) -> float:
    """Mean Gaussian negative log-likelihood per answer (3-DoF, without the constant)."""
    _, logdet = np.linalg.slogdet(cov)
    d2 = np.einsum("ni,ni->n", error, np.linalg.solve(cov, error[..., None])[..., 0])
    return float(0.5 * (logdet + d2).mean())


def quantile_scales(error: np.ndarray, cov0: np.ndarray, level: float = 0.95) -> tuple[float, float]:
    """(k_t, k_r) that put ``level`` of these rows' position errors inside the ``level`` ellipse of the scaled model's
    position block (``scaled``) and ``level`` of their heading errors inside the ``level`` interval of its heading
    variance. The prior makes the shares depend on the two scales only nearly separately: a few alternating rounds of
    bisection (in log scale) on each."""
    def share_pos(k_t: float, k_r: float) -> float:
        c = scaled(cov0, k_t, k_r)
        d2 = np.einsum("ni,ni->n", error[:, :2], np.linalg.solve(c[:, :2, :2], error[:, :2, None])[..., 0])
        return float(np.mean(d2 <= stats.chi2.ppf(level, 2)))

    def share_yaw(k_t: float, k_r: float) -> float:
        c = scaled(cov0, k_t, k_r)
        return float(np.mean(error[:, 2] ** 2 / c[:, 2, 2] <= stats.chi2.ppf(level, 1)))

    def solve(share: object, lo: float = 1e-3, hi: float = 1e5) -> float:
        """The smallest scale (to 1e-4 relative) whose share reaches ``level``."""
        for _ in range(60):
            mid = math.sqrt(lo * hi)
            if share(mid) >= level:  # type: ignore[operator]
                hi = mid
            else:
                lo = mid
        return hi

    k_t = k_r = 1.0
    for _ in range(3):
        k_t = solve(lambda k, k_r=k_r: share_pos(k, k_r))
        k_r = solve(lambda k, k_t=k_t: share_yaw(k_t, k))
    return k_t, k_r


def shipped(cov0: np.ndarray, compensated: np.ndarray, params: dict[str, float]) -> np.ndarray:
    """(M, 3, 3) the shipped model: each row scaled by its kind's (motion-compensated or rigid) scales."""
    return np.where(compensated[:, None, None],
                    scaled(cov0, params["position_scale"], params["heading_scale"]),
                    scaled(cov0, params["rigid_position_scale"], params["rigid_heading_scale"]))


def fit(error: np.ndarray, cov0: np.ndarray, compensated: np.ndarray) -> dict[str, dict[str, float]]:
    """Every model's parameters on these rows (module docstring). A kind of answer (motion-compensated, rigid) with no
    rows keeps the other kind's scales (reported as such: ``*_rows`` 0)."""
    k_t, k_r = quantile_scales(error[compensated], cov0[compensated]) if compensated.any() else (math.nan, math.nan)
    rk_t, rk_r = quantile_scales(error[~compensated], cov0[~compensated]) if (~compensated).any() else (k_t, k_r)
    if not compensated.any():
        k_t, k_r = rk_t, rk_r
    ks = optimize.minimize(lambda p: nll(error, scaled(cov0, *np.exp(p))), np.log([20.0, 80.0]),
                           method="Nelder-Mead", options={"xatol": 1e-6, "fatol": 1e-9, "maxiter": 2000}).x
    kf = optimize.minimize(lambda p: nll(error, floored(cov0, *np.exp(p))), np.log([10.0, 10.0, 0.02, 0.003]),
                           method="Nelder-Mead", options={"xatol": 1e-7, "fatol": 1e-9, "maxiter": 8000}).x
    # the constant model's ML is closed form: the mean squared errors
    a = math.sqrt(float((error[:, :2] ** 2).mean()))
    b = math.sqrt(float((error[:, 2] ** 2).mean()))
    return {"shipped": {"position_scale": k_t, "heading_scale": k_r, "rigid_position_scale": rk_t,
                        "rigid_heading_scale": rk_r, "compensated_rows": int(compensated.sum()),
                        "rigid_rows": int((~compensated).sum())},
            "scaled-ML": {"position_scale": float(np.exp(ks[0])), "heading_scale": float(np.exp(ks[1]))},
            "scaled+floor": {"position_scale": float(np.exp(kf[0])), "heading_scale": float(np.exp(kf[1])),
                             "position_floor_m": float(np.exp(kf[2])),
                             "heading_floor_deg": math.degrees(float(np.exp(kf[3])))},
            "constant": {"position_sigma_m": a, "heading_sigma_deg": math.degrees(b)}}


def report(error: np.ndarray, cov: np.ndarray) -> dict[str, float]:
    """Calibration figures of ``cov`` against ``error`` (``benchmark.metrics.covariance_report``, as ``reradar bench``
    reports them), the mean negative log-likelihood and the Spearman correlations of predicted and actual error
    sizes (position, heading; nan for a constant model, which predicts one size)."""
    from reradar_core.benchmark.metrics import covariance_report

    out: dict[str, float] = {**covariance_report(error, cov), "nll": nll(error, cov)}
    size = np.sqrt(cov[:, 0, 0] + cov[:, 1, 1])
    out["spearman_pos"] = (float(stats.spearmanr(size, np.hypot(error[:, 0], error[:, 1]))[0])
                           if np.ptp(size) > 0 else math.nan)
    out["spearman_yaw"] = (float(stats.spearmanr(np.sqrt(cov[:, 2, 2]), np.abs(error[:, 2]))[0])
                           if np.ptp(cov[:, 2, 2]) > 0 else math.nan)
    return out


def main() -> None:
    from reradar_core.localization.confidence_fit import SPLIT_MODELS

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--splits", default=",".join(SPLIT_MODELS), help="comma-separated training splits")
    ap.add_argument("--step", type=int, default=2, help="every step-th query scan of each session")
    ap.add_argument("--data", default=None, help="collected rows (.npz): read when it exists (several, comma-separated: "
                    "all read and pooled), else collected and written")
    ap.add_argument("--out", type=Path, default=None, help="write the fitted parameters and the table as JSON")
    args = ap.parse_args()
    splits = [s for s in args.splits.split(",") if s]
    files = [Path(f) for f in args.data.split(",") if f] if args.data else []
    if files and all(f.exists() for f in files):
        loaded = [np.load(f) for f in files]
        data = {k: np.concatenate([z[k] for z in loaded]) for k in loaded[0].files}
    else:
        data = collect(splits, args.step)
        if files:
            np.savez_compressed(files[0], **data)
    fitting = ~data["heldout"]
    params = fit(data["error"][fitting], data["cov0"][fitting], data["compensated"][fitting])
    sh, sc, fl, co = params["shipped"], params["scaled-ML"], params["scaled+floor"], params["constant"]
    print(f"shipped (95 % inside): position_scale {sh['position_scale']:.2f}, heading_scale {sh['heading_scale']:.2f} "
          f"({sh['compensated_rows']} motion-compensated answers); rigid_position_scale {sh['rigid_position_scale']:.2f}, "
          f"rigid_heading_scale {sh['rigid_heading_scale']:.2f} ({sh['rigid_rows']} rigid); "
          f"scaled-ML: position_scale {sc['position_scale']:.2f}, heading_scale {sc['heading_scale']:.2f}; "
          f"scaled+floor: {fl['position_scale']:.2f}, {fl['heading_scale']:.2f}, {fl['position_floor_m']:.4f} m, "
          f"{fl['heading_floor_deg']:.4f} deg; constant: {co['position_sigma_m']:.4f} m, {co['heading_sigma_deg']:.4f} deg (fit on {fitting.sum()} answers)")
    table = []
    groups = {name: data["split"] == name for name in sorted(set(data["split"]))}
    groups.update({"all": np.ones(len(fitting), bool), "all, motion-compensated answers": data["compensated"],
                   "all, rigid answers": ~data["compensated"]})
    for name, group in groups.items():
        for part, mask in (("fit", fitting), ("held out", data["heldout"])):
            m = mask & group
            if not m.any():
                continue
            e = data["error"][m]
            for model, cov in (("shipped", shipped(data["cov0"][m], data["compensated"][m], sh)),
                               ("scaled-ML", scaled(data["cov0"][m], sc["position_scale"], sc["heading_scale"])),
                               ("scaled+floor", floored(data["cov0"][m], fl["position_scale"], fl["heading_scale"],
                                                        fl["position_floor_m"], math.radians(fl["heading_floor_deg"]))),
                               ("constant", constant(int(m.sum()), co["position_sigma_m"],
                                                     math.radians(co["heading_sigma_deg"])))):
                row = {"split": name, "part": part, "model": model, **report(e, cov)}
                table.append(row)
    print("| split | rows | model | n | NEES | inside 50 / 90 / 95 / 99 % (3-DoF) | position inside 95 % | heading inside 95 % | NLL | "
          "Spearman pos / yaw | RMS pos m (predicted) | RMS yaw deg (predicted) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in table:
        print(f"| {r['split']} | {r['part']} | {r['model']} | {r['n']} | {r['nees']:.2f} | "
              f"{r['inside_50_pct']:.1f} / {r['inside_90_pct']:.1f} / {r['inside_95_pct']:.1f} / "
              f"{r['inside_99_pct']:.1f} | {r['position_inside_95_pct']:.1f} | {r['heading_inside_95_pct']:.1f} | "
              f"{r['nll']:.2f} | {r['spearman_pos']:.2f} / {r['spearman_yaw']:.2f} | {r['rms_position_m']:.3f} "
              f"({r['predicted_rms_position_m']:.3f}) | {r['rms_heading_deg']:.3f} ({r['predicted_rms_heading_deg']:.3f}) |")
    if args.out is not None:
        args.out.write_text(json.dumps({"params": params, "table": table}, indent=1))


if __name__ == "__main__":
    main()
