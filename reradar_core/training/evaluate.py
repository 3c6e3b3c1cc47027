"""Quick retrieval check of a model on a simulator suite: global-descriptor Recall@1, database vs queries.

This is the model card's check (``python -m reradar_core.training.evaluate --suite smoke --models default``);
the full benchmark with pose estimation and baselines is ``reradar bench``.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from reradar_core.evaluation.metrics import recall_at_1
from reradar_core.model import DescriptorExtractor

__all__ = ["suite_recall_at_1"]


def suite_recall_at_1(extractors: list[DescriptorExtractor], suite: str,
                      progress: bool = False) -> list[dict[str, float]]:
    """Recall@1 of each extractor's global descriptors per query sequence of ``suite`` (all queries in the
    denominator, the suite's radius) plus, per query sequence, the fraction of queries that have a database
    scan within the radius. Cartesian images are rendered once and shared (all models must use the same
    ``CartesianConfig`` and canonical-heading setting: the images are ``cartesian_image``'s)."""
    from reradar_core.sim.suites import build_suite

    first = extractors[0]
    if any(e.cartesian != first.cartesian or e.config.canonical_heading != first.config.canonical_heading
           for e in extractors):
        raise ValueError("all extractors must share one Cartesian configuration and canonical-heading setting")
    data = build_suite(suite, progress=progress)

    def images(path):
        seq = data.load(path)  # the network's input image (``cartesian_image``: at its heading too), shared
        return np.stack([first.cartesian_image(seq.load_scan(i)) for i in range(len(seq))]), seq.poses.xy

    db = [images(p) for p in data.database]
    db_img, db_xy = np.concatenate([d[0] for d in db]), np.concatenate([d[1] for d in db])
    queries = {p.name: images(p) for p in data.queries}
    out: list[dict[str, float]] = []
    for ex in extractors:
        def desc(imgs, ex=ex):
            """(projected global descriptors, raw NetVLAD vectors)."""
            g, v = [], []
            with torch.inference_mode():
                for i in range(0, len(imgs), 16):
                    fmap = ex.net.backbone(ex.net.mask_input(torch.from_numpy(imgs[i:i + 16].astype(np.float32))[:, None]))
                    g.append(ex.net.aggregate(fmap).numpy())
                    v.append(ex.net.vlad(fmap).numpy())
            return np.concatenate(g), np.concatenate(v)

        dd, dv = desc(db_img)
        res: dict[str, float] = {}
        for name, (qi, qxy) in queries.items():
            qd, qv = desc(qi)
            top = np.argmax(qd @ dd.T, axis=1)
            res[name] = recall_at_1(qxy, db_xy[top], data.radius_m)
            res[f"{name}:raw_netvlad"] = recall_at_1(qxy, db_xy[np.argmax(qv @ dv.T, axis=1)], data.radius_m)
            dist = np.hypot(qxy[:, None, 0] - db_xy[None, :, 0], qxy[:, None, 1] - db_xy[None, :, 1])
            res[f"{name}:with_revisit"] = float((dist.min(axis=1) <= data.radius_m).mean())
        out.append(res)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default="smoke")
    ap.add_argument("--models", nargs="+", default=["default"])
    args = ap.parse_args()
    exs = [DescriptorExtractor.from_pretrained(m) for m in args.models]
    for m, ex, r in zip(args.models, exs, suite_recall_at_1(exs, args.suite), strict=True):
        print(m, ex.model_id, json.dumps(r), flush=True)


if __name__ == "__main__":
    main()
