"""ReRadar's far view (``reradar_core.localization.far_view``) on a calibration route: every query localized in the
near view alone and with the far view for refused answers, split by open land (``WorldProfile.open_share``).

The subset and overrides are those of ``calibrate_sim.py`` (``--set world.seed=N --set route.seed=N``: another
world and route of the suite's definition, not the benchmark's own query drive), so a choice about the far view
is made on routes the benchmark does not score. Two readings of a refused answer's place are reported (Recall@1
counts the place an answer names, localized or not):

    screened   the best-screened candidate (as the near view has always reported it)
    top1       the answering view's global-descriptor top 1
    place      the shipped rule, ``TwoViewResult.place_id`` (two views only): the far top 1 only when the near
               view held fewer landmarks than ``FarViewConfig.sparse_landmarks``, else the near best-screened

and the global descriptors alone, before any screen (``*_desc``: each view's nearest map descriptor; ``two_desc``:
the far view's for a query whose near view held fewer landmarks than ``sparse_landmarks``, else the near view's -
``baselines.ours.two_view_top1``, the two-view method's descriptor-alone figure),

and for both, the answers' success rate (localized within the suite's radius and 10 degrees) and wrong poses
(localized outside them). One JSON row per run (``--json`` appends).

    OPENBLAS_NUM_THREADS=1 python benchmarks/probe_far_view.py --suite offroad-sim-hard --model our-3-offroad-w05 \\
        --set world.seed=23 --set route.seed=23 --label route23
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import calibrate_sim as C  # noqa: E402

from reradar_core.baselines import make_method  # noqa: E402
from reradar_core.baselines.ours import Ours, _far_part, prepared_to_features, two_view_top1  # noqa: E402
from reradar_core.geometry.se2 import wrap_angle  # noqa: E402
from reradar_core.localization import localize_two_views  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    C.add_route_arguments(ap)
    ap.add_argument("--no-cache", action="store_true", help="neither read nor write the render cache")
    ap.add_argument("--dense", action="store_true",
                    help="the far view with its dense registration (method <model>+dense, matching.dense)")
    ap.add_argument("--far-sparse", type=int, default=None,
                    help="FarViewConfig.sparse_landmarks (default 512): a larger value lets the dense step run after "
                         "full near views too (a probe setting; it also changes which place a refused answer names)")
    ap.add_argument("--dense-candidates", type=int, default=None,
                    help="FarViewConfig.dense_candidates (default 5): how many far candidates the dense step registers")
    ap.add_argument("--far-z-q", type=float, default=None,
                    help="the far view's landmark threshold (FarViewConfig.landmark_z_q; default: the near view's)")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    method = make_method(a.model + ("+dense" if a.dense else "+far"))
    if a.far_z_q is not None or a.far_sparse is not None or a.dense_candidates is not None:  # other probe settings
        fv = method.far_view if a.far_z_q is None else replace(method.far_view, landmark_z_q=a.far_z_q)
        fv = fv if a.far_sparse is None else replace(fv, sparse_landmarks=a.far_sparse)
        fv = fv if a.dense_candidates is None else replace(fv, dense_candidates=a.dense_candidates)
        method = Ours(method.extractor, method.localization, name=method.name, far_view=fv, dense=a.dense)
    route = C.prepare_route(a, method, use_cache=not a.no_cache)
    db, qs, db_pose, q_pose, radius, ov = (route.db, route.queries, route.db_pose, route.q_pose, route.radius,
                                           route.overrides)
    index = method.build_index([method.describe_prepared(p) for p in db])
    method.ready_database(index, db, db_pose)
    near_map, far_map = method.localizer(index, db, db_pose), method._far_localizer

    def place_ok(j: int, i: int) -> bool:
        return bool(np.hypot(*(db_pose[j, :2] - q_pose[i, :2])) <= radius)

    def pose_ok(r, i: int) -> bool:  # type: ignore[no-untyped-def]
        e = r.T_map_query - q_pose[i]
        return bool(np.hypot(e[0], e[1]) <= radius and abs(np.rad2deg(wrap_angle(e[2]))) <= 10.0)

    def top1(r) -> int:  # type: ignore[no-untyped-def]
        return int(min(r.candidates, key=lambda c: c.rank).keyframe_id)

    rec: dict[str, list[bool]] = {k: [] for k in ("near_screened", "near_top1", "two_screened", "two_top1",
                                                   "near_sr", "two_sr", "near_wrong", "two_wrong", "far_used",
                                                   "two_place", "near_sparse", "dense_used", "near_desc",
                                                   "far_desc", "two_desc")}
    dense_kf = (lambda j: np.asarray(db[j]["dense"], np.float32)) if a.dense else None
    for i, qp in enumerate(qs):
        dense_q = (lambda qp=qp: np.asarray(qp["dense"], np.float32)) if a.dense else None
        out = localize_two_views(near_map, prepared_to_features(qp), far_map,
                                 lambda qp=qp: prepared_to_features(_far_part(qp)), method.localization,
                                 method.far_view, dense_q, dense_kf)
        for tag, r in (("near", out.near_result), ("two", out.result)):
            rec[f"{tag}_screened"].append(place_ok(int(r.best.keyframe_id), i))
            rec[f"{tag}_top1"].append(place_ok(int(r.best.keyframe_id) if r.localized else top1(r), i))
            rec[f"{tag}_sr"].append(r.localized and pose_ok(r, i))
            rec[f"{tag}_wrong"].append(r.localized and not pose_ok(r, i))
        rec["two_place"].append(place_ok(int(out.place_id), i))  # the shipped rule (TwoViewResult.place_id)
        rec["near_sparse"].append(out.near_sparse)
        rec["far_used"].append(out.view == "far")
        rec["dense_used"].append(out.registration == "dense")
        near_top = int(near_map.index.search(np.asarray(qp["global"], np.float32), 1)[0][0, 0])
        far_top = int(far_map.index.search(np.asarray(qp["far_global"], np.float32), 1)[0][0, 0])
        rec["near_desc"].append(place_ok(near_top, i))
        rec["far_desc"].append(place_ok(far_top, i))
        rec["two_desc"].append(place_ok(two_view_top1(qp, near_map.index, far_map.index, method.far_view), i))
    world = C.subset_world(a.suite, ov)
    is_open = np.array([world.is_open_land(p) for p in q_pose[:, :2]], dtype=bool)
    row: dict[str, object] = {"label": a.label, "suite": a.suite, "model": a.model, "far_z_q": a.far_z_q,
                              "dense": a.dense, "far_sparse": a.far_sparse, "dense_candidates": a.dense_candidates,
                              "window": a.window,
                              "overrides": ov, "queries": len(qs), "database": len(db),
                              "open_pct": round(100 * is_open.mean(), 1)}
    for k, v in rec.items():
        if k in ("far_used", "near_sparse", "dense_used"):
            row[k] = int(np.sum(v))
            continue
        h = np.asarray(v, bool)
        row[k] = round(100 * h.mean(), 2)
        if k.endswith(("screened", "top1", "place", "desc")):
            row[f"{k}_open"] = round(100 * h[is_open].mean(), 1) if is_open.any() else None
    row["seconds"] = round(time.perf_counter() - t0, 1)
    C.emit_row(row, a.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
