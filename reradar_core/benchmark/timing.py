"""Stage timings of the paper's "Computational Time" section, measured on this machine.

Stages per query scan (batch size one): polar -> Cartesian conversion, global descriptor (network forward
incl. NetVLAD / whitening), landmark pose estimation (Cen 2018 detection, local descriptors sampled from F',
mutual-NN matching and RANSAC against the top-k candidates), and database retrieval (exact inner-product
search with FAISS over the map's global descriptors).
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from reradar_core.features import ScanFeatures
from reradar_core.io.scan import RadarScan

__all__ = ["stage_timings", "STAGES"]

STAGES = ("polar_to_cartesian", "global_descriptor", "landmark_pose_estimation", "retrieval", "total")


def stage_timings(extractor: Any, query_scans: Sequence[RadarScan], db_features: Sequence[ScanFeatures],
                  db_poses: np.ndarray, localization: Any = None, warmup: int = 1) -> dict[str, Any]:
    """Time each stage on every query scan; returns ``{"stages_ms": {stage: {"mean", "median"}}, ...}``.

    Args:
        extractor: ``DescriptorExtractor`` (uses its ``cartesian_image``, ``run_images`` and keypoint
            sampling).
        query_scans: scans to time (the first ``warmup`` are run once more, untimed, first).
        db_features: the map's features; db_poses: (N, 3) keyframe poses.
        localization: ``LocalizationConfig`` (default settings when None).
    """
    import faiss

    from reradar_core.landmarks import detect_landmarks
    from reradar_core.localization import KeyframeCandidates, LocalizationConfig, localize

    cfg = localization or LocalizationConfig()
    db = np.ascontiguousarray(np.stack([f.global_descriptor for f in db_features]).astype(np.float32))
    index = faiss.IndexFlatIP(db.shape[1])
    index.add(db)
    k = min(cfg.num_to_retrieve, len(db_features))
    keyframes = KeyframeCandidates(db_features.__getitem__, cfg.alignment.grid_cell_m)  # grids kept, as the service

    rows: list[list[float]] = []
    scans = list(query_scans[:warmup]) + list(query_scans)
    for n, scan in enumerate(scans):
        t0 = time.perf_counter()
        img = extractor.cartesian_image(scan)
        t1 = time.perf_counter()
        g, fmap = extractor.run_images(img[None])
        t2 = time.perf_counter()
        _, idx = index.search(np.ascontiguousarray(g[:1], dtype=np.float32), k)
        t3 = time.perf_counter()
        lm = detect_landmarks(scan, extractor.landmark_config)
        feats = extractor._features(scan, g[0], fmap[0], lm)  # keypoints + local descriptors from F'
        cands = [keyframes.candidate(int(j), db_poses[j], float(np.linalg.norm(db[j] - g[0])), r)
                 for r, j in enumerate(idx[0]) if j >= 0]
        localize(feats, cands, cfg)
        t4 = time.perf_counter()
        if n >= warmup:
            rows.append([(t1 - t0) * 1e3, (t2 - t1) * 1e3, (t4 - t3) * 1e3, (t3 - t2) * 1e3, (t4 - t0) * 1e3])
    arr = np.asarray(rows)
    load = os.getloadavg()[0]
    return {"stages_ms": {s: {"mean": float(arr[:, i].mean()), "median": float(np.median(arr[:, i]))}
                          for i, s in enumerate(STAGES)},
            "n_scans": len(rows), "n_database": len(db_features), "load_average_1min": load,
            "model": getattr(extractor, "name", "") or getattr(extractor, "model_id", "")}
