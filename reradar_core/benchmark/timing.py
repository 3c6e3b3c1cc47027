"""Stage timings of the paper's "Computational Time" section, measured on this machine.

Stages per query scan (batch size one): polar -> Cartesian conversion, global descriptor (network forward
incl. NetVLAD / whitening), landmark pose estimation (Cen 2018 detection, local descriptors sampled from F',
then the ``Localizer``'s landmark-alignment screen and guided pose estimate of the candidates), and database
retrieval (the ``Localizer``'s FAISS search over the map's global descriptors). Localization runs through the
same ``Localizer`` as the service and the benchmark's ``Ours``.
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
        extractor: ``DescriptorExtractor`` (uses its ``cartesian_image``, ``run_images`` and
            ``features_from_outputs``).
        query_scans: scans to time (the first ``warmup`` are run once more, untimed, first).
        db_features: the map's features; db_poses: (N, 3) keyframe poses.
        localization: ``LocalizationConfig`` (default settings when None).
    """
    from reradar_core.localization import InMemoryKeyframes, LocalizationConfig, Localizer
    from reradar_core.retrieval import GlobalIndex

    cfg = localization or LocalizationConfig()
    db = np.stack([f.global_descriptor for f in db_features]).astype(np.float32)
    localizer = Localizer(GlobalIndex(db), InMemoryKeyframes(list(db_features), db_poses), cfg)
    if cfg.checks_place_repetition:  # measured with the map, as a built map stores it: not a query's stage
        localizer.place_repetitions(cfg)

    rows: list[list[float]] = []
    scans = list(query_scans[:warmup]) + list(query_scans)
    for n, scan in enumerate(scans):
        t0 = time.perf_counter()
        img = extractor.cartesian_image(scan)
        t1 = time.perf_counter()
        g, fmap = extractor.run_images(img[None])
        t2 = time.perf_counter()
        # landmarks detected as ``describe`` detects them (the extractor's settings), keypoints + local descriptors
        feats = extractor.features_from_outputs(scan, g[0], fmap[0])
        res = localizer.localize(feats, cfg)
        t3 = time.perf_counter()
        retrieve_ms = res.timings_ms.get("retrieve_ms", 0.0)
        if n >= warmup:
            rows.append([(t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3 - retrieve_ms, retrieve_ms,
                         (t3 - t0) * 1e3])
    arr = np.asarray(rows)
    load = os.getloadavg()[0]
    return {"stages_ms": {s: {"mean": float(arr[:, i].mean()), "median": float(np.median(arr[:, i]))}
                          for i, s in enumerate(STAGES)},
            "n_scans": len(rows), "n_database": len(db_features), "load_average_1min": load,
            "model": getattr(extractor, "name", "") or getattr(extractor, "model_id", "")}
