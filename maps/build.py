"""Build a keyframe map from radar scans with known poses (batched feature extraction, atomic write)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np
from tqdm import tqdm

from maps.store import MapMetadata, MapWriter
from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.io.scan import RadarScan
from reradar_core.localization.extractor import FeatureExtractor
from reradar_core.localization.keyframes import select_keyframes  # re-exported: the map builder's rule

__all__ = ["select_keyframes", "cap_keypoints", "build_map", "build_map_from_sequence"]

logger = logging.getLogger(__name__)

ProgressFn = Callable[[int, int], None]


def cap_keypoints(features: ScanFeatures, max_keypoints: int | None) -> ScanFeatures:
    """Keep at most ``max_keypoints`` keypoints, evenly spread over the detector's order (deterministic)."""
    n = features.keypoints_xy_m.shape[0]
    if max_keypoints is None or n <= max_keypoints:
        return features
    keep = np.unique(np.linspace(0, n - 1, max_keypoints).round().astype(np.int64))
    return ScanFeatures(features.global_descriptor, features.keypoints_xy_m[keep],
                        features.local_descriptors[keep], features.timestamp_us)


def build_map(
    out: str | Path,
    extractor: FeatureExtractor,
    load_scan: Callable[[int], RadarScan],
    poses: np.ndarray,
    *,
    radar_preset: str,
    name: str = "",
    source: str = "",
    batch_size: int = 8,
    max_keypoints: int | None = None,
    overwrite: bool = False,
    progress: ProgressFn | None = None,
    show_progress: bool = False,
) -> Path:
    """Describe scans ``load_scan(0..N-1)`` in batches and write an HDF5 map at ``out`` (atomically).

    Args:
        out: map file to write.
        extractor: the descriptor model (its id and weights hash go into the map).
        load_scan: returns scan i.
        poses: (N, 3) float64 ``T_map_keyframe`` of each scan (x m, y m, yaw rad) at its mid-sweep time
            (``Sequence.mid_sweep_poses``, docs/CONVENTIONS.md; the map records ``pose_time = mid_sweep``).
        radar_preset: preset name recorded in the map.
        batch_size: scans per network batch.
        max_keypoints: optional cap on stored keypoints per keyframe (map size).
        progress: called with (done, total) after each batch (background jobs report through it).
        show_progress: show a tqdm bar.

    Returns:
        ``out``.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    n = len(poses)
    if n == 0:
        raise ConfigError("cannot build a map from zero scans")
    if batch_size < 1:
        raise ConfigError(f"batch_size must be >= 1, got {batch_size}")
    writer: MapWriter | None = None
    bar = tqdm(total=n, desc=f"build-map {Path(out).name}", unit="scan", disable=not show_progress)
    try:
        for start in range(0, n, batch_size):
            stop = min(n, start + batch_size)
            scans = [load_scan(i) for i in range(start, stop)]
            feats = [cap_keypoints(f, max_keypoints) for f in extractor.describe_batch(scans)]
            if writer is None:
                meta = MapMetadata(
                    model_id=str(extractor.model_id),
                    weights_sha256=str(extractor.weights_sha256),
                    radar_preset=radar_preset,
                    cartesian_width_px=int(extractor.cartesian.width_px),
                    cartesian_resolution_m=float(extractor.cartesian.resolution_m),
                    descriptor_dim=int(feats[0].global_descriptor.shape[0]),
                    local_descriptor_dim=int(feats[0].local_descriptors.shape[1]),
                    source=source,
                    name=name or Path(out).stem,
                )
                writer = MapWriter(out, meta, overwrite=overwrite).__enter__()
            for i, (scan, f) in enumerate(zip(scans, feats, strict=True)):
                writer.add(f, poses[start + i], timestamp_us=scan.timestamp_us)
            bar.update(stop - start)
            if progress is not None:
                progress(stop, n)
    except BaseException as exc:
        if writer is not None:
            writer.__exit__(type(exc), exc, exc.__traceback__)
        raise
    finally:
        bar.close()
    assert writer is not None
    writer.__exit__(None, None, None)
    logger.info("wrote map %s with %d keyframes", out, n)
    return Path(out)


def build_map_from_sequence(sequence_dir: str | Path, out: str | Path, extractor: FeatureExtractor, *,
                            layout: str | None = None, preset: str | None = None, min_spacing_m: float = 0.0,
                            time_unit: str | None = None, **kwargs: object) -> Path:
    """Build a map from a sequence folder in any supported layout (``reradar_core.io.datasets``).

    ``time_unit`` is the unit of the pose file's timestamps (``s``, ``ms``, ``us``, ``ns``) where they are not
    absolute UTC times (``load_sequence``'s ``pose_time_unit``); None: never guessed."""
    from reradar_core.io.datasets import load_sequence

    seq = load_sequence(sequence_dir, layout=layout, preset=preset, pose_time_unit=time_unit)
    keep = select_keyframes(seq.poses.poses, min_spacing_m)
    seq = seq.subset(keep)
    kwargs.setdefault("source", f"{seq.layout}:{Path(sequence_dir).resolve()}")
    kwargs.setdefault("name", seq.name)
    # keyframe poses at mid-sweep: what a registration against the keyframe's whole sweep aligns
    # (docs/CONVENTIONS.md)
    return build_map(out, extractor, seq.load_scan, seq.mid_sweep_poses(), radar_preset=seq.preset.name,
                     **kwargs)  # type: ignore[arg-type]
