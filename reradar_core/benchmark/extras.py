"""Add-ons of a benchmark run that concern ReRadar only: stage timings and the yaw-consistency curve."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from reradar_core.baselines.base import PlaceRecognitionMethod
from reradar_core.benchmark.runner import BenchConfig, BenchPair, prepare_sequence

__all__ = ["add_timing", "add_yaw_consistency", "YAW_ANGLES_DEG"]

logger = logging.getLogger(__name__)

#: Controlled yaw rotations of the consistency curve, degrees.
YAW_ANGLES_DEG = np.arange(0.0, 360.1, 15.0)


def add_timing(results: dict[str, Any], ours: PlaceRecognitionMethod, pair: BenchPair, config: BenchConfig,
               n_scans: int, threads: int) -> dict[str, Any]:
    """Measure ReRadar's stage timings on ``n_scans`` query scans of ``pair`` -> ``results["timing"]``."""
    from reradar_core.baselines.ours import prepared_to_features
    from reradar_core.benchmark.timing import stage_timings

    db = prepare_sequence([ours], pair.database, config)[ours.name].records
    feats = [prepared_to_features(r) for r in db]
    n = min(n_scans, len(pair.query))
    scans = [pair.query.load_scan(i) for i in range(n)]
    t = stage_timings(ours.extractor, scans, feats, pair.database.poses.poses,  # type: ignore[attr-defined]
                      getattr(ours, "localization", None))
    t.update(threads=threads, sequence=pair.name, method=ours.name)
    results["timing"] = t
    return t


def add_yaw_consistency(results: dict[str, Any], ours: Sequence[PlaceRecognitionMethod], pair: BenchPair,
                        out_dir: Path, n_scans: int = 4) -> Path | None:
    """Yaw-consistency curve of F' for every ReRadar model given (ReResNet and ResNet ablations) on the first
    ``n_scans`` query scans -> ``results["yaw_consistency"]`` and ``out_dir/yaw_consistency.png``."""
    from reradar_core.benchmark.plots import plot_yaw_consistency
    from reradar_core.benchmark.yaw import yaw_consistency

    scans = [pair.query.load_scan(i) for i in range(min(n_scans, len(pair.query)))]
    curves: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for m in ours:
        ex = m.extractor  # type: ignore[attr-defined]
        backbone = getattr(getattr(ex, "config", None), "backbone", "?")
        s = yaw_consistency(ex, scans, YAW_ANGLES_DEG)
        curves[f"{m.name} ({backbone})"] = (YAW_ANGLES_DEG, s)
    if not curves:
        return None
    results["yaw_consistency"] = {k: {"angles_deg": a.tolist(), "consistency": s.tolist()}
                                  for k, (a, s) in curves.items()}
    path = plot_yaw_consistency(curves, Path(out_dir) / "yaw_consistency.png")
    results.setdefault("figures", []).append(path.name)
    return path
