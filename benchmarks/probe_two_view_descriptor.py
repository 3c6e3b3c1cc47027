"""The two-view method's descriptor alone on a calibration route (issue 11: "the global descriptor alone within 3
points of the full pipeline"; docs/MODEL.md, "The two-view descriptor").

Every revisit query of a ``calibrate_sim.py`` render subset (``--set world.seed=N --set route.seed=N``: another world and
route of the suite's definition, never the benchmark's own drive) is described in both views (``<model>+far``'s
features) and each reading's nearest map keyframes are judged against the suite's radius, with no landmark screen:

    near        the near view's descriptor (the paper's 201 px at 0.64 m)
    far         the far view's (257 px at 1.28 m)
    two         the shipped two-view reading (``far_view.retrieval_view``): far for a query whose near view holds fewer
                landmarks than ``FarViewConfig.sparse_landmarks`` (512), else near
    two@N       the same with a landmark bar of N (probe readings, not shipped)
    sum_sparse  sparse queries by the sum of both views' cosines, the others by the near view

Recall@1 and Recall@20 (the right place among the 20 nearest: what a screen of 20 candidates can find), in %, one JSON
row per run (``--json`` appends).

    OPENBLAS_NUM_THREADS=1 python benchmarks/probe_two_view_descriptor.py --suite offroad-sim-hard \\
        --model our-3-offroad-w05 --set world.seed=23 --set route.seed=23 --label hard23
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import calibrate_sim as C  # noqa: E402

from reradar_core.baselines import make_method  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    C.add_route_arguments(ap)
    ap.add_argument("--bars", default="128,256,384", help="other landmark bars of the two@N readings")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    method = make_method(a.model + "+far")
    route = C.prepare_route(a, method)
    db, qs, db_pose, q_pose, radius = route.db, route.queries, route.db_pose, route.q_pose, route.radius

    def sims(key: str) -> np.ndarray:  # (Q, N) cosines of unit descriptors
        return np.stack([p[key] for p in qs]).astype(np.float64) @ np.stack([p[key] for p in db]).astype(np.float64).T

    s_near, s_far = sims("global"), sims("far_global")
    landmarks = np.array([len(p["keypoints"]) for p in qs])
    dist = np.hypot(q_pose[:, None, 0] - db_pose[None, :, 0], q_pose[:, None, 1] - db_pose[None, :, 1])

    def recall(s: np.ndarray, k: int) -> np.ndarray:  # (Q,) bool: a keyframe within the radius among the k nearest
        top = np.argsort(-s, axis=1, kind="stable")[:, :k]
        return (np.take_along_axis(dist, top, 1) <= radius).any(1)

    def gated(bar: int) -> np.ndarray:
        return np.where((landmarks < bar)[:, None], s_far, s_near)

    sparse = landmarks < method.far_view.sparse_landmarks
    readings = {"near": s_near, "far": s_far, "two": gated(method.far_view.sparse_landmarks),
                "sum_sparse": np.where(sparse[:, None], s_near + s_far, s_near)}
    readings.update({f"two@{int(b)}": gated(int(b)) for b in a.bars.split(",") if b})
    row: dict[str, object] = {"label": a.label, "suite": a.suite, "model": a.model, "window": a.window,
                              "overrides": route.overrides, "queries": len(qs), "database": len(db), "sparse": int(sparse.sum()),
                              "sparse_landmarks": sorted(int(n) for n in landmarks[sparse])}
    for name, s in readings.items():
        row[f"{name}_r1"] = round(100 * float(recall(s, 1).mean()), 2)
        row[f"{name}_r20"] = round(100 * float(recall(s, 20).mean()), 2)
    row["seconds"] = round(time.perf_counter() - t0, 1)
    C.emit_row(row, a.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
