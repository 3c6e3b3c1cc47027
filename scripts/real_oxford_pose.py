"""Full pose path on real Oxford Radar RobotCar scans against ground-truth odometry.

Cen 2018 landmarks -> local descriptors sampled from F' -> mutual nearest-neighbour matching -> RANSAC 2-D
rigid transform, for every scan pair 1..10 frames apart (about 2-20 m). Reports, per frame gap, the mean
translation error e_t (m), rotation error e_r (deg), RANSAC success and the paper's localization success
(e_t < 25 m and e_r < 10 deg, OORD radius) plus a strict success (e_t < 1 m, e_r < 2 deg).

With ``--localizer`` every pair instead runs through the service's ``Localizer`` (the shipped
``LocalizationConfig``: floor, confidence bar, deeper search) on a one-keyframe map holding the earlier scan at
its odometry pose, and the table counts, per gap, the answers ``localized`` within 2 m / 2 deg (correct),
``localized`` outside them (a confident wrong pose, what issue 11 forbids) and refused, with the confidences.

With ``--leave-one-out`` every scan runs through the ``Localizer`` on a map of the other ten (mid-sweep poses and times,
so the answers are motion-compensated as on a served map). Both ``Localizer`` modes also check the answers' pose
covariance against their errors (``benchmark.metrics.covariance_report``).

Usage:
    python scripts/real_oxford_pose.py ../shared/data/real-oxford [--model default] [--max-keypoints 512]
    python scripts/real_oxford_pose.py ../shared/data/real-oxford --leave-one-out
    python scripts/real_oxford_pose.py ../shared/data/real-oxford --rotate-seed 0 --localizer
    python scripts/real_oxford_pose.py ../shared/data/real-oxford --localizer --far-view only       # the far view alone
    python scripts/real_oxford_pose.py ../shared/data/real-oxford --localizer --far-view fallback   # as '+far'
    python scripts/real_oxford_pose.py ../shared/data/real-oxford --localizer --far-view dense      # as '+dense'
    python scripts/real_oxford_pose.py ../shared/data/real-oxford --dense-pairs   # dense registration alone, no gate
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

import numpy as np

from reradar_core.benchmark.metrics import covariance_report
from reradar_core.evaluation.metrics import localization_errors, localization_success, pose_error, radius_for
from reradar_core.geometry.se2 import relative_pose
from reradar_core.io.datasets import load_sequence
from reradar_core.localization import FarViewConfig
from reradar_core.matching import (
    AlignmentConfig,
    RansacConfig,
    estimate_pose_guided,
    estimate_rigid_2d,
    match_descriptors,
)
from reradar_core.model import DescriptorExtractor


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", help="real-oxford folder (radar/<t>.png + radar_odometry.csv)")
    ap.add_argument("--model", default="default", help="shipped model name or .pt path")
    ap.add_argument("--max-keypoints", type=int, default=512, help="strongest landmarks kept (0 = all)")
    ap.add_argument("--max-gap", type=int, default=10)
    ap.add_argument("--ratio", type=float, default=None, help="Lowe ratio for matching (default: off)")
    ap.add_argument("--pose-method", choices=("guided", "mutual_nn"), default="guided",
                    help="guided (library default: descriptor-guided hypotheses scored by landmark alignment) or "
                         "mutual_nn (the paper's mutual nearest neighbours + RANSAC)")
    ap.add_argument("--rotate-seed", type=int, default=None,
                    help="turn every query scan by a random whole-azimuth heading (seeded) before describing it")
    ap.add_argument("--json", default=None, help="also write the per-gap table as JSON here")
    ap.add_argument("--leave-one-out", action="store_true",
                    help="run every scan through the service's Localizer on a map of the other scans (mid-sweep poses "
                         "and times from the odometry, so every keyframe's motion is known and the answers are "
                         "motion-compensated, as on a served map); count the answers and check their pose covariance")
    ap.add_argument("--localizer", action="store_true",
                    help="run every pair through the service's Localizer on a one-keyframe map (shipped floor, "
                         "confidence bar and search) and count correct / wrong / refused answers")
    ap.add_argument("--far-view", choices=("only", "fallback", "dense"), default=None,
                    help="ReRadar's far view (257 px at 1.28 m/px, the whole range; reradar_core.localization."
                         "far_view): 'only' describes every scan in it instead of the model's own image (every mode); "
                         "'fallback' (--localizer / --leave-one-out) localizes refused answers again in it, as the "
                         "'+far' benchmark method does; 'dense' also registers answers both views refused by "
                         "whole-image correlation, as '+dense' does (matching.dense)")
    ap.add_argument("--dense-pairs", action="store_true",
                    help="register every pair by the far view's dense registration alone (matching.dense, no gate; "
                         "mid-sweep ground truth): per gap, pairs within 2 m / 2 deg, median errors and the smallest "
                         "heading and shift margins, against the bars the far view applies")
    args = ap.parse_args()
    if args.dense_pairs:
        _dense_pairs(load_sequence(args.folder, layout="oxford"), args.max_gap)
        return

    seq = load_sequence(args.folder, layout="oxford")
    ex = DescriptorExtractor.from_pretrained(args.model, max_keypoints=args.max_keypoints or None)
    far_ex = ex.with_view(FarViewConfig().cartesian) if args.far_view else None
    if args.far_view == "only":
        ex, far_ex = far_ex, None
    elif args.far_view in ("fallback", "dense") and not (args.localizer or args.leave_one_out):
        ap.error(f"--far-view {args.far_view} needs --localizer or --leave-one-out")
    scans = [seq.load_scan(i) for i in range(len(seq))]
    feats = [ex.describe(s) for s in scans]  # the landmarks the service detects (the extractor's settings)
    poses = seq.poses.poses
    qfeats, dyaw = feats, np.zeros(len(scans))
    if args.rotate_seed is not None:
        # rolling the rows by -k shows every return k azimuth steps earlier (clockwise azimuths,
        # docs/CONVENTIONS.md): the scene turns counter-clockwise by k * 2 pi / A in the query frame, i.e. the
        # query sensor turned clockwise, so T_i_j's yaw drops by that angle
        shift = np.random.default_rng(args.rotate_seed).integers(0, scans[0].num_azimuths, len(scans))
        turned = [replace(s, power=np.roll(s.power, -int(k), axis=0)) for s, k in zip(scans, shift, strict=True)]
        qfeats = [ex.describe(s) for s in turned]
        dyaw = shift * 2 * np.pi / scans[0].num_azimuths
    # the far view's features of every map scan and query (fallback mode), or None
    args.far = None if far_ex is None else ([far_ex.describe(s) for s in scans],
                                            [far_ex.describe(s) for s in (turned if args.rotate_seed is not None
                                                                          else scans)])
    # the far view's dense images of every map scan and query (dense mode), or None
    args.dense = None
    if args.far_view == "dense":
        from reradar_core.matching.dense import dense_image

        fv = FarViewConfig()
        args.dense = ([dense_image(s, fv.cartesian, fv.dense) for s in scans],
                      [dense_image(s, fv.cartesian, fv.dense) for s in (turned if args.rotate_seed is not None
                                                                          else scans)])
    print(f"pose method {args.pose_method}; model {ex.name} ({ex.model_id}), {len(scans)} scans, "
          f"{np.mean([len(f.keypoints_xy_m) for f in feats]):.0f} keypoints per scan in the image")
    if args.leave_one_out:
        _leave_one_out(feats, qfeats, seq.mid_sweep_poses(), dyaw, args)
        return
    if args.localizer:
        _localizer_table(feats, qfeats, poses, dyaw, args)
        return
    cfg = RansacConfig()
    radius = radius_for("oxford")
    rows = []
    print("| gap (frames) | pairs | mean distance (m) | matches | inliers | RANSAC ok | mean e_t (m) | "
          "mean e_r (deg) | success (25 m, 10 deg) | strict (1 m, 2 deg) | wrong but ok (> 2 m or 2 deg) | "
          "max ambiguity |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for gap in range(1, args.max_gap + 1):
        et, er, ok, nm, ni, dist, wrong, amb = [], [], [], [], [], [], [], []
        for i in range(len(scans) - gap):
            j = i + gap
            T_i_j_gt = relative_pose(poses[i], poses[j])
            T_i_j_gt[2] -= dyaw[j]
            if args.pose_method == "guided":
                m = qfeats[j].keypoints_xy_m  # "matches" column = query landmarks for the guided verifier
                est = estimate_pose_guided(qfeats[j].keypoints_xy_m, qfeats[j].local_descriptors,
                                           feats[i].keypoints_xy_m, feats[i].local_descriptors, AlignmentConfig())
            else:
                m = match_descriptors(qfeats[j].local_descriptors, feats[i].local_descriptors, ratio=args.ratio)
                est = estimate_rigid_2d(qfeats[j].keypoints_xy_m[m[:, 0]], feats[i].keypoints_xy_m[m[:, 1]], cfg)
            e_t, e_r = localization_errors(est.pose[None] if est.success else np.full((1, 3), np.nan),
                                           T_i_j_gt[None])
            et.append(float(e_t[0]))
            er.append(float(e_r[0]))
            ok.append(bool(est.success))
            nm.append(len(m))
            ni.append(int(est.num_inliers))
            dist.append(float(np.hypot(*T_i_j_gt[:2])))
            raw_t, raw_r = localization_errors(est.pose[None], T_i_j_gt[None])
            wrong.append(bool(est.success) and not bool(localization_success(raw_t, raw_r, 2.0, 2.0)[0]))
            amb.append(float(getattr(est, "ambiguity", float("nan"))))
        et_a, er_a = np.array(et), np.array(er)
        succ = localization_success(et_a, er_a, radius)
        strict = localization_success(et_a, er_a, 1.0, 2.0)
        row = {"gap": gap, "pairs": len(et), "distance_m": float(np.mean(dist)), "matches": float(np.mean(nm)),
               "inliers": float(np.mean(ni)), "ransac_ok": float(np.mean(ok)),
               "mean_e_t_m": float(np.nanmean(et_a)) if np.isfinite(et_a).any() else float("nan"),
               "mean_e_r_deg": float(np.nanmean(er_a)) if np.isfinite(er_a).any() else float("nan"),
               "success": float(succ.mean()), "strict_success": float(strict.mean()),
               "wrong_but_ok": int(np.sum(wrong)), "max_ambiguity": float(np.nanmax(amb)) if np.isfinite(amb).any()
               else float("nan")}
        rows.append(row)
        print(f"| {gap} | {row['pairs']} | {row['distance_m']:.1f} | {row['matches']:.0f} | {row['inliers']:.0f} | "
              f"{row['ransac_ok']:.0%} | {row['mean_e_t_m']:.2f} | {row['mean_e_r_deg']:.2f} | "
              f"{row['success']:.0%} | {row['strict_success']:.0%} | {row['wrong_but_ok']} | "
              f"{row['max_ambiguity']:.2f} |")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"model": ex.name, "model_id": ex.model_id, "rows": rows}, fh, indent=2)


def _dense_pairs(seq: object, max_gap: int) -> None:
    """Every pair (i, j = i + gap) registered by ``register_dense`` on the far view's images (module docstring)."""
    from reradar_core.geometry.se2 import wrap_angle
    from reradar_core.matching.dense import dense_image, register_dense

    fv = FarViewConfig()
    scans = [seq.load_scan(i) for i in range(len(seq))]  # type: ignore[attr-defined]
    images = [dense_image(s, fv.cartesian, fv.dense) for s in scans]
    poses = seq.mid_sweep_poses()  # type: ignore[attr-defined]
    print("| gap (frames) | pairs | mean distance (m) | within 2 m / 2 deg | median e_t (m) | median e_r (deg) | "
          f"min heading margin (bar {fv.dense_min_heading_margin}) | min shift margin (bar {fv.dense_min_shift_margin}) |")
    print("|---|---|---|---|---|---|---|---|")
    for gap in range(1, max_gap + 1):
        rows = []
        for i in range(len(scans) - gap):
            j = i + gap
            gt = relative_pose(poses[i], poses[j])
            reg = register_dense(images[j], images[i], fv.cartesian, fv.dense)
            e_t = float(np.hypot(*(reg.T_keyframe_query[:2] - gt[:2])))
            e_r = float(abs(np.rad2deg(wrap_angle(reg.T_keyframe_query[2] - gt[2]))))
            rows.append((float(np.hypot(*gt[:2])), e_t, e_r, reg.heading_margin, reg.shift_margin))
        if not rows:
            continue
        a = np.array(rows)
        ok = int(np.sum((a[:, 1] <= 2.0) & (a[:, 2] <= 2.0)))
        print(f"| {gap} | {len(a)} | {a[:, 0].mean():.1f} | {ok} | {np.median(a[:, 1]):.2f} | {np.median(a[:, 2]):.2f} | "
              f"{a[:, 3].min():.3f} | {a[:, 4].min():.3f} |")


def _localize(feats: list, qfeats: list, keys: list[int], j: int, poses: np.ndarray, config: object,
              args: argparse.Namespace) -> object:
    """Query j through a ``Localizer`` on a map of the scans ``keys`` (at ``poses``); with ``args.far`` (the far
    view's map and query features) a refused answer is localized again in the far view (``localize_two_views``)."""
    from reradar_core.localization import InMemoryKeyframes, Localizer, localize_two_views
    from reradar_core.retrieval import GlobalIndex

    def map_of(fs: list) -> Localizer:
        keyframes = InMemoryKeyframes([fs[i] for i in keys], poses[keys], np.array([fs[i].timestamp_us for i in keys]))
        g = np.stack([np.asarray(fs[i].global_descriptor, np.float32).reshape(-1) for i in keys])
        return Localizer(GlobalIndex(g), keyframes, config)  # type: ignore[arg-type]

    if args.far is None:
        return map_of(feats).localize(qfeats[j])
    far_feats, far_qfeats = args.far
    dense_q = dense_kf = None
    if args.dense is not None:  # keyframe k of the map is scan keys[k]
        dense_q, dense_kf = (lambda: args.dense[1][j]), (lambda k: args.dense[0][keys[k]])
    return localize_two_views(map_of(feats), qfeats[j], map_of(far_feats), lambda: far_qfeats[j],
                              dense_query=dense_q, dense_keyframe=dense_kf).result


def _localizer_table(feats: list, qfeats: list, poses: np.ndarray, dyaw: np.ndarray, args: argparse.Namespace) -> None:
    """Per gap: the ``Localizer``'s answers for query j on the map {scan i = j - gap at poses[i]}."""
    from reradar_core.localization import LocalizationConfig

    config = LocalizationConfig()
    print("| gap (frames) | pairs | mean distance (m) | localized within 2 m / 2 deg | localized outside (wrong) | "
          "refused | confidence of correct answers (min) | confidence of wrong answers (max) | refusal reasons |")
    print("|---|---|---|---|---|---|---|---|---|")
    rows: list[dict[str, object]] = []
    n_good = n_bad = n_refused = 0
    all_wrong: list[tuple[int, int, float, float, float]] = []
    cov_errors: list[np.ndarray] = []  # the correct answers' errors and covariances (the pose covariance's check)
    covariances: list[np.ndarray] = []
    for gap in range(1, args.max_gap + 1):
        good, bad, refused, dist, conf_good, conf_bad, reasons = 0, 0, 0, [], [], [], []
        for i in range(len(feats) - gap):
            j = i + gap
            T_map_query_gt = poses[j].copy()
            T_map_query_gt[2] -= dyaw[j]  # the query scan was turned (see main)
            res = _localize(feats, qfeats, [i], j, poses, config, args)
            dist.append(float(np.hypot(*(poses[j][:2] - poses[i][:2]))))
            if not res.localized or res.T_map_query is None:
                refused += 1
                reasons.append(str(res.reason))
                continue
            e_t, e_r = localization_errors(res.T_map_query[None], T_map_query_gt[None])
            if localization_success(e_t, e_r, 2.0, 2.0)[0]:
                good += 1
                conf_good.append(res.confidence)
                if res.pose_covariance is not None:
                    cov_errors.append(pose_error(T_map_query_gt, res.T_map_query))
                    covariances.append(res.pose_covariance)
            else:
                bad += 1
                conf_bad.append(res.confidence)
                all_wrong.append((i, j, float(e_t[0]), float(e_r[0]), res.confidence))
        n_good, n_bad, n_refused = n_good + good, n_bad + bad, n_refused + refused
        lo_good, hi_bad = min(conf_good, default=float("nan")), max(conf_bad, default=float("nan"))
        why = sorted(set(reasons))
        rows.append({"gap": gap, "pairs": good + bad + refused, "distance_m": float(np.mean(dist)), "correct": good,
                     "wrong": bad, "refused": refused, "min_confidence_correct": lo_good,
                     "max_confidence_wrong": hi_bad, "refusal_reasons": why})
        print(f"| {gap} | {good + bad + refused} | {np.mean(dist):.1f} | {good} | {bad} | {refused} | "
              f"{lo_good:.3f} | {hi_bad:.3f} | {', '.join(why) or '-'} |")
    total = {"pairs": n_good + n_bad + n_refused, "correct": n_good, "wrong": n_bad, "refused": n_refused}
    print(f"\nall pairs: {total['pairs']}, localized within 2 m / 2 deg {total['correct']}, localized outside "
          f"(wrong) {total['wrong']}, refused {total['refused']}")
    for i, j, off_m, off_deg, c in all_wrong:
        print(f"  wrong: scan {i} -> {j}: {off_m:.2f} m, {off_deg:.2f} deg off at confidence {c:.3f}")
    calibration = covariance_report(np.array(cov_errors), np.array(covariances)) if cov_errors else None
    if calibration is not None:
        _print_calibration(calibration)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"mode": "localizer", "rows": rows, "total": total, "pose_covariance": calibration}, fh,
                      indent=2)


def _leave_one_out(feats: list, qfeats: list, poses: np.ndarray, dyaw: np.ndarray, args: argparse.Namespace) -> None:
    """Each scan j localized by the ``Localizer`` on a map of every other scan (``poses``: mid-sweep, with the scans'
    times): correct (within 2 m / 2 deg), wrong and refused answers, the mean errors, and the pose covariance's
    calibration over the correct ones (``benchmark.metrics.covariance_report``)."""
    from reradar_core.localization import LocalizationConfig

    config = LocalizationConfig()
    good, bad, refused = 0, [], 0
    errors, covariances, e_t_all, e_r_all = [], [], [], []
    for j in range(len(feats)):
        others = [i for i in range(len(feats)) if i != j]
        res = _localize(feats, qfeats, others, j, poses, config, args)
        if not res.localized or res.T_map_query is None:
            refused += 1
            continue
        gt = poses[j].copy()
        gt[2] -= dyaw[j]  # the query scan was turned (see main)
        e_t, e_r = localization_errors(res.T_map_query[None], gt[None])
        if not localization_success(e_t, e_r, 2.0, 2.0)[0]:
            bad.append((j, float(e_t[0]), float(e_r[0]), res.confidence))
            continue
        good += 1
        e_t_all.append(float(e_t[0]))
        e_r_all.append(float(e_r[0]))
        if res.pose_covariance is not None:
            errors.append(pose_error(gt, res.T_map_query))
            covariances.append(res.pose_covariance)
    print(f"leave-one-out: {len(feats)} scans, localized within 2 m / 2 deg {good} (mean {np.mean(e_t_all):.3f} m / "
          f"{np.mean(e_r_all):.3f} deg), localized outside (wrong) {len(bad)}, refused {refused}")
    for j, off_m, off_deg, c in bad:
        print(f"  wrong: scan {j}: {off_m:.2f} m, {off_deg:.2f} deg off at confidence {c:.3f}")
    calibration = covariance_report(np.array(errors), np.array(covariances)) if errors else None
    if calibration is not None:
        _print_calibration(calibration)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"mode": "leave-one-out", "correct": good, "wrong": len(bad), "refused": refused,
                       "mean_e_t_m": float(np.mean(e_t_all)) if e_t_all else None,
                       "mean_e_r_deg": float(np.mean(e_r_all)) if e_r_all else None,
                       "pose_covariance": calibration}, fh, indent=2)


def _print_calibration(c: dict) -> None:
    """One line of ``covariance_report``'s figures."""
    print(f"pose covariance over the {c['n']} correct answers: NEES {c['nees']:.2f} (3 when calibrated), inside its "
          f"50 / 90 / 95 / 99 % ellipsoids {c['inside_50_pct']:.1f} / {c['inside_90_pct']:.1f} / "
          f"{c['inside_95_pct']:.1f} / {c['inside_99_pct']:.1f} %, RMS error {c['rms_position_m']:.3f} m / "
          f"{c['rms_heading_deg']:.3f} deg (predicted {c['predicted_rms_position_m']:.3f} m / "
          f"{c['predicted_rms_heading_deg']:.3f} deg)")


if __name__ == "__main__":
    main()
