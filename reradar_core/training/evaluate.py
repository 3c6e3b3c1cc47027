"""Quick retrieval check of a model on a simulator suite: global-descriptor Recall@1, database vs queries.

This is the model card's check (``python -m reradar_core.training.evaluate --suite smoke --models default``);
the full benchmark with pose estimation and baselines is ``reradar bench``.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from reradar_core.evaluation.metrics import recall_at_1
from reradar_core.model import DescriptorExtractor

__all__ = ["suite_recall_at_1"]


def suite_recall_at_1(ex: DescriptorExtractor, suite: str, progress: bool = False) -> dict[str, float]:
    """Recall@1 of ``ex``'s global descriptors per query sequence of ``suite`` (all queries in the
    denominator, the suite's radius), plus the count of queries with a database scan within the radius."""
    from reradar_core.sim.suites import build_suite

    data = build_suite(suite, progress=progress)
    db_seqs = data.database_sequences()
    db_desc = np.concatenate([ex.global_descriptors([s.load_scan(i) for i in range(len(s))]) for s in db_seqs])
    db_xy = np.concatenate([s.poses.xy for s in db_seqs])
    out: dict[str, float] = {}
    for qpath in data.queries:
        q = data.load(qpath)
        qd = ex.global_descriptors([q.load_scan(i) for i in range(len(q))])
        top = np.argmax(qd @ db_desc.T, axis=1)
        out[f"{qpath.name}"] = recall_at_1(q.poses.xy, db_xy[top], data.radius_m)
        d = np.hypot(q.poses.xy[:, None, 0] - db_xy[None, :, 0], q.poses.xy[:, None, 1] - db_xy[None, :, 1])
        out[f"{qpath.name}:with_revisit"] = float((d.min(axis=1) <= data.radius_m).mean())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default="smoke")
    ap.add_argument("--models", nargs="+", default=["default"])
    args = ap.parse_args()
    res = {}
    for m in args.models:
        ex = DescriptorExtractor.from_pretrained(m)
        res[m] = suite_recall_at_1(ex, args.suite)
        print(m, ex.model_id, json.dumps(res[m]), flush=True)


if __name__ == "__main__":
    main()
