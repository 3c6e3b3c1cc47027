"""The global descriptors alone on a calibration route: near view, far view, and two ways to combine them.

Session 34 asked whether the far view's descriptor could carry more of the retrieval (issue 11: the descriptor alone
within 3 points of the pipeline) or name the place of an answer both views refuse better than its top 1
(``TwoViewResult.place_id``). Every query of a calibration route (``calibrate_sim.py``'s ``--set world.seed=N --set
route.seed=N``: another world and route of the suite's definition, not the benchmark's drive) is described in both
views, and Recall@1 of the revisits (a map scan within the suite's radius) is reported for

    near / far         each view's descriptor alone (inner product of the L2-normalised descriptors)
    sum w=W            near similarity + W x far similarity (a fused descriptor; it would cost a far pass per query)
    zsum               the two similarities z-scored over the map, summed
    far smooth S m     far similarity averaged over map keyframes with Gaussian weights of S m (map side)

over all revisits, those in open land (``World.is_open_land``) and those whose near view held fewer landmarks than
``FarViewConfig.sparse_landmarks`` (the queries whose refused place the far top 1 names). One JSON row per route.

    OPENBLAS_NUM_THREADS=1 python benchmarks/probe_far_descriptor.py --set world.seed=23 --set route.seed=23
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import calibrate_sim as C  # noqa: E402

from reradar_core.baselines import make_method  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    C.add_route_arguments(ap)
    a = ap.parse_args(argv)
    method = make_method(a.model + "+far")
    route = C.prepare_route(a, method)
    db, qs, db_pose, q_pose, radius, ov = (route.db, route.queries, route.db_pose, route.q_pose, route.radius,
                                           route.overrides)
    sim_near = np.stack([p["global"] for p in qs]) @ np.stack([p["global"] for p in db]).T
    sim_far = np.stack([p["far_global"] for p in qs]) @ np.stack([p["far_global"] for p in db]).T
    dist = np.hypot(q_pose[:, None, 0] - db_pose[None, :, 0], q_pose[:, None, 1] - db_pose[None, :, 1])
    revisit = dist.min(axis=1) <= radius
    world = C.subset_world(a.suite, ov)
    is_open = np.array([world.is_open_land(p) for p in q_pose[:, :2]], dtype=bool)
    sparse = np.array([len(p["keypoints"]) for p in qs]) < method.far_view.sparse_landmarks

    def recall(sim: np.ndarray) -> dict[str, float]:
        hit = dist[np.arange(len(sim)), sim.argmax(axis=1)] <= radius
        return {k: round(100 * float(hit[revisit & m].mean()), 1) if (revisit & m).any() else float("nan")
                for k, m in (("all", np.ones_like(hit)), ("open", is_open), ("sparse", sparse))}

    def zscore(s: np.ndarray) -> np.ndarray:
        return (s - s.mean(axis=1, keepdims=True)) / s.std(axis=1, keepdims=True)

    kf_dist = np.hypot(db_pose[:, None, 0] - db_pose[None, :, 0], db_pose[:, None, 1] - db_pose[None, :, 1])
    rows: dict[str, dict[str, float]] = {"near": recall(sim_near), "far": recall(sim_far)}
    for w in (0.5, 1.0, 2.0):
        rows[f"sum w={w}"] = recall(sim_near + w * sim_far)
    rows["zsum"] = recall(zscore(sim_near) + zscore(sim_far))
    for sigma in (5.0, 10.0, 20.0):
        weights = np.exp(-0.5 * (kf_dist / sigma) ** 2)
        rows[f"far smooth {sigma:g} m"] = recall(sim_far @ (weights / weights.sum(axis=1, keepdims=True)).T)
    out = {"suite": a.suite, "model": a.model, "overrides": ov, "revisits": int(revisit.sum()),
           "open": int((revisit & is_open).sum()), "sparse": int((revisit & sparse).sum()), "recall_at_1": rows}
    C.emit_row(out, a.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
