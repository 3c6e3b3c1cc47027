"""Build a keyframe map from radar scans with known poses (batched feature extraction, the map's place
repetition measured on what is stored, atomic write)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from maps.paths import far_view_path
from maps.store import MapMetadata, MapWriter
from reradar_core.errors import ConfigError, PoseFileError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.se2 import check_poses, check_yaw_radians
from reradar_core.io.scan import RadarScan
from reradar_core.localization import (
    InMemoryKeyframes,
    KeyframeSource,
    LocalizationConfig,
    Localizer,
    RepetitionTable,
)
from reradar_core.localization.extractor import FeatureExtractor
from reradar_core.localization.far_view import FarViewConfig
from reradar_core.localization.keyframes import select_keyframes  # re-exported: the map builder's rule
from reradar_core.localization.pose_clock import (
    PoseClockConfig,
    consecutive_registrations,
    pose_clock_message,
    pose_clock_offset,
)
from reradar_core.matching.dense import DenseConfig, dense_image, dense_image_settings
from reradar_core.matching.motion import keyframe_twists, time_neighbours
from reradar_core.retrieval import GlobalIndex

__all__ = ["select_keyframes", "cap_keypoints", "build_map", "build_map_from_sequence", "measure_place_repetition",
           "add_place_repetition", "unjudged_warning", "motion_warning", "MOTION_UNKNOWN_WARN_SHARE", "REPETITION_CACHE_KEYFRAMES", "UNJUDGED_WARN_SHARE"]

#: Keyframes whose screen data the place-repetition pass keeps in memory (~50 KB each: ~400 MB at most); a larger
#: map is read back through an LRU of this size (the pass goes along the map, so neighbours stay cached; rivals
#: beyond it are read again, ~1.3 ms each).
REPETITION_CACHE_KEYFRAMES = 8_000

logger = logging.getLogger(__name__)

ProgressFn = Callable[[int, int], None]


#: Fewest keypoints a keyframe may be capped to: a pose needs at least ``LocalizationConfig.min_inliers`` (default
#: 12) aligned landmarks, and with fewer stored than that no query can be localized on the keyframe.
_MIN_MAP_KEYPOINTS = 12


def cap_keypoints(features: ScanFeatures, max_keypoints: int | None) -> ScanFeatures:
    """Keep at most ``max_keypoints`` keypoints, evenly spread over the detector's order (deterministic)."""
    n = features.keypoints_xy_m.shape[0]
    if max_keypoints is None or n <= max_keypoints:
        return features
    keep = np.unique(np.linspace(0, n - 1, max_keypoints).round().astype(np.int64))
    return ScanFeatures(features.global_descriptor, features.keypoints_xy_m[keep],
                        features.local_descriptors[keep], features.timestamp_us)


def measure_place_repetition(keyframes: KeyframeSource, global_descriptors: np.ndarray, config: LocalizationConfig,
                             workers: int | None = None, progress: ProgressFn | None = None,
                             show_progress: bool = False) -> RepetitionTable:
    """Every keyframe's place repetition (``Localizer.place_repetitions``) with ``config``'s settings; ~20-40 ms per
    keyframe and thread.

    Args:
        keyframes: the map's keyframes as stored (a ``MapWriter``'s read back, or an open ``KeyframeMap``).
        global_descriptors: (N, D) float32 unit global descriptors, row i = keyframe i.
        workers: threads (default: the usable cores, at most 4).
        progress: called with (done, total) as keyframes are measured.
        show_progress: show a tqdm bar.
    """
    n = len(keyframes)
    localizer = Localizer(GlobalIndex(np.asarray(global_descriptors, np.float32)), keyframes, config,
                          cache_size=None if n <= REPETITION_CACHE_KEYFRAMES else REPETITION_CACHE_KEYFRAMES)
    bar = tqdm(total=n, desc="place repetition", unit="keyframe", disable=not show_progress)

    def step(done: int, total: int) -> None:
        bar.update(done - bar.n)
        if progress is not None:
            progress(done, total)

    try:
        return localizer.place_repetitions(config, workers=workers, progress=step)
    finally:
        bar.close()


#: Share of a map's keyframes the repeated-place check may be unable to judge before the build warns.
UNJUDGED_WARN_SHARE = 0.1


def unjudged_warning(table: RepetitionTable, num_keyframes: int) -> str | None:
    """A sentence for the user when over ``UNJUDGED_WARN_SHARE`` of the keyframes have no keyframe of their own place
    aligning with them (the repeated-place check cannot judge them: a street that repeats itself is then answered
    on whichever copy wins), else None."""
    k = table.unjudged
    if num_keyframes == 0 or k <= UNJUDGED_WARN_SHARE * num_keyframes:
        return None
    return (f"{k} of {num_keyframes} keyframes have no keyframe of their own place (within the place radius, 20 m by "
            f"default) that aligns with them, so the repeated-place check cannot judge answers on them; build the "
            f"map with keyframes closer together (--min-spacing-m well under the radius; docs/MODEL.md 'Repeated "
            f"places')")


#: Share of a map's keyframes whose motion on the map drive may be unknown before the build warns.
MOTION_UNKNOWN_WARN_SHARE = 0.1


def motion_warning(poses: np.ndarray, timestamps_us: np.ndarray, config: LocalizationConfig | None = None,
                   known: np.ndarray | None = None) -> str | None:
    """A sentence for the user when over ``MOTION_UNKNOWN_WARN_SHARE`` of the keyframes have no known motion on the
    map drive (``matching.motion.keyframe_twists`` under ``config.motion``), so answers on them keep the rigid pose
    (not motion-compensated), with the reason that applies: no keyframe within ``max_keyframe_gap_s`` in time (a
    sparser map, or a single keyframe), or neighbours whose times and poses are no drive's (e.g. a wrong time unit);
    else None. ``known``: (N,) bool, the ``keyframe_twists`` flags when the caller has them."""
    motion = (config or LocalizationConfig()).motion
    n = len(poses)
    if not motion.enabled or n == 0:
        return None
    stamps = np.asarray(timestamps_us, np.int64)
    if known is None:
        _, known = keyframe_twists(np.asarray(poses, np.float64), stamps, motion)
    unknown = int((~known).sum())
    if unknown <= MOTION_UNKNOWN_WARN_SHARE * n:
        return None
    head = (f"{unknown} of {n} keyframes have no known motion on the map drive, so answers on them are not "
            f"motion-compensated (the rigid registration's pose, 1.2-4.8x the translation error on the benchmark "
            f"suites; docs/CONVENTIONS.md 'Motion compensation')")
    if n == 1:
        return head + ": a map of one keyframe has no neighbour in time to take its motion from"
    # which keyframes have a neighbour in time within the gap: those unknown anyway are no drive's
    order, has_before, has_after = time_neighbours(stamps, motion.max_keyframe_gap_s)
    near = np.zeros(n, bool)
    near[order] = has_before | has_after
    far, odd = int((~known & ~near).sum()), int((~known & near).sum())
    parts = []
    if far:
        parts.append(f"{far} have no keyframe within {motion.max_keyframe_gap_s:g} s of them (keep keyframes closer "
                     f"in time: a smaller --min-spacing-m, or more of the drive's scans)")
    if odd:
        parts.append(f"{odd} have neighbours whose times and poses are no drive's (faster than "
                     f"{motion.max_speed_mps:g} m/s or turning over 90 deg between them: check the pose file's time "
                     f"unit)")
    return head + ": " + "; ".join(parts)


def add_place_repetition(path: str | Path, out: str | Path | None = None, localization: LocalizationConfig | None = None,
                         workers: int | None = None, show_progress: bool = False,
                         overwrite: bool = False) -> RepetitionTable:
    """Measure the place repetition of the map at ``path`` under ``localization`` (default ``LocalizationConfig()``)
    and store it (``maps.store.store_place_repetition``: into a copy installed atomically at ``out``, default over
    ``path``; an existing ``out`` only with ``overwrite``), replacing one it holds: for maps built before
    ``build-map`` stored it, or with ``--no-place-repetition``. Returns the table."""
    from maps.store import open_map, store_place_repetition

    with open_map(path, read_place_repetition=False) as m:  # a damaged table is what this replaces
        assert m.global_descriptors is not None
        sha = m.content_sha256()
        table = measure_place_repetition(m, m.global_descriptors, localization or LocalizationConfig(), workers,
                                         show_progress=show_progress)
    store_place_repetition(path, table, out, expect_sha256=sha, overwrite=overwrite)
    return table


def _heartbeat(progress: ProgressFn | None, done: int, total: int) -> Callable[..., None]:
    """``beat(force=False)``: ``progress(done, total)`` at most about once a second (at once with ``force``), for a
    build's passes after its scans are described (a job's heartbeat and cancel check keep running)."""
    last = [time.monotonic()]

    def beat(force: bool = False) -> None:
        if progress is not None and (force or time.monotonic() - last[0] >= 1.0):
            last[0] = time.monotonic()
            progress(done, total)

    return beat


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
    place_repetition: bool = True,
    localization: LocalizationConfig | None = None,
    repetition_workers: int | None = None,
    far_view: FarViewConfig | None = None,
    dense: DenseConfig | None = None,
    pose_clock: PoseClockConfig | None = PoseClockConfig(),
    pose_at: Callable[[np.ndarray], np.ndarray] | None = None,
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
        progress: called with (done, total) after each batch (background jobs report through it), and again with
            the last (done, total) about once a second while the pose clock is checked and the place repetition is
            measured (a job's heartbeat and cancel check keep running). ``total`` counts scan descriptions: N, or 2 N with ``far_view``, whose
            pass over the scans (done N + 1 ... 2 N; about as long again as the map's: docs/BENCHMARKS.md, "Session 34") follows the map's.
        show_progress: show a tqdm bar.
        place_repetition: measure every keyframe's place repetition (``Localizer.place_repetitions``, ~20-40 ms
            per keyframe and thread) and store it in the map, so that no query pays for it (the repeated-place
            check, ``LocalizationConfig.max_place_repetition``); False: a map without it (measured as keyframes
            first win, in every process).
        localization: the settings it is measured with (default ``LocalizationConfig()``); a localizer with other
            settings ignores the stored table. Settings without the check (``checks_place_repetition`` False) store
            none.
        repetition_workers: threads for that pass (default: the usable cores, at most 4).
        far_view: also write the far-view companion ``far_view_path(out)`` (the same scans, poses and times
            described by ``extractor.with_view(far_view.cartesian)``; ReRadar's far view, docs/MODEL.md), which a
            served map uses for the answers its own view refuses. None: no companion (and an old one at that path
            is removed, since it would describe another map). The companion holds every keyframe's dense image
            (``far_view.dense``) for the far view's dense registration.
        dense: store every keyframe's dense image (``matching.dense.dense_image`` of its scan in the extractor's
            geometry, ~90 KB per 257 px keyframe) with these settings; None (default for a map itself): none.
        pose_clock: check that the poses run on the scans' clock (``localization.pose_clock``: every keyframe
            registered against the one before, 5-25 ms a pair, and the turns compared with the poses'); a pose file
            off by more than a sweep is refused (``PoseFileError``, saying by how much and what to add). None: no
            check (the far-view companion's build: the map's own checked the same poses).
        pose_at: the pose file's pose (3,) at any scan time (µs (M,) -> (M, 3), at its mid-sweep time as ``poses``;
            NaN rows beyond the file: ``io.datasets.pose_file_reader``), which the check reads at shifted times;
            None: ``poses`` interpolated between keyframes (enough for scans a sweep or two apart; keyframes seconds
            apart cut corners, and a shift is judged only on the pairs it keeps inside the keyframes' span).

    Returns:
        ``out``.

    Raises:
        PoseFileError: the poses are off the scans' clock (``pose_clock``); nothing is written.
    """
    if far_view is not None and not hasattr(extractor, "with_view"):
        raise ConfigError(f"model {extractor.model_id!r} cannot describe a far view (no with_view)")
    poses = check_poses(poses, "keyframe poses")
    check_yaw_radians(poses, "keyframe poses")
    n = len(poses)
    if n == 0:
        raise ConfigError("cannot build a map from zero scans")
    if batch_size < 1:
        raise ConfigError(f"batch_size must be >= 1, got {batch_size}")
    if max_keypoints is not None and max_keypoints < 1:  # 0 built a map nothing could localize on; -1 failed in numpy
        raise ConfigError(f"max_keypoints must be >= 1 (or None: no cap), got {max_keypoints}")
    if max_keypoints is not None and max_keypoints < _MIN_MAP_KEYPOINTS:
        logger.warning("max_keypoints %d is below the %d aligned landmarks a localized answer needs by default "
                       "(LocalizationConfig.min_inliers): no query will be localized on this map with the default "
                       "settings", max_keypoints, _MIN_MAP_KEYPOINTS)
    total = n if far_view is None else 2 * n  # scan descriptions: the far view describes every scan again
    writer: MapWriter | None = None
    sparse: list[int] = []  # keyframes with fewer landmarks than a localized answer needs
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
                writer = MapWriter(out, meta, overwrite=overwrite,
                                   dense_settings=None if dense is None else dense_image_settings(dense)).__enter__()
            for i, (scan, f) in enumerate(zip(scans, feats, strict=True)):
                image = None if dense is None else dense_image(scan, extractor.cartesian, dense)
                writer.add(f, poses[start + i], timestamp_us=scan.timestamp_us, dense_image=image)
                if len(f.keypoints_xy_m) < _MIN_MAP_KEYPOINTS:
                    sparse.append(start + i)
            bar.update(stop - start)
            if progress is not None:
                progress(stop, total)
        bar.close()
        assert writer is not None
        if sparse and (max_keypoints is None or max_keypoints >= _MIN_MAP_KEYPOINTS):  # a blank sweep (a dropped frame, a covered radome) became a keyframe nothing can match (QA)
            logger.warning("%s: %d of %d keyframes hold fewer than %d landmarks (scan %s%s): no query can be localized "
                           "on them (blank or nearly blank sweeps?)", Path(out).name, len(sparse), n,
                           _MIN_MAP_KEYPOINTS, ", ".join(str(i) for i in sparse[:5]), " ..." if len(sparse) > 5 else "")
        config = localization or LocalizationConfig()
        if pose_clock is not None and n >= 2:  # before the map is measured and installed: poses of other instants
            clock_beat = _heartbeat(progress, n, total)
            align = replace(config.alignment, min_inliers=config.min_inliers)  # the pose estimator's (verify_candidate)
            T_prev_next, ratio = consecutive_registrations(writer.read_keyframe, n, align, lambda _i: clock_beat())
            clock = pose_clock_offset(T_prev_next, ratio, writer.timestamps_us, writer.poses, pose_clock, pose_at)
            if clock.offset_detected:
                raise PoseFileError(pose_clock_message(clock, "the keyframe poses"))
            if clock.pairs == 0:  # said, so that a straight drive's map is not taken as checked (QA session 41)
                logger.warning("%s: the pose file's clock could not be checked against the scans': fewer than %d "
                               "consecutive keyframes turn by %g degrees or more and register (a straight drive? keyframes "
                               "out of time order?); "
                               "make sure the pose file's times are the scans' (docs/MODEL.md 'The pose clock')",
                               Path(out).name, pose_clock.min_pairs, pose_clock.min_turn_deg)
        if place_repetition and config.checks_place_repetition:  # else no query would read it
            repetition_beat = _heartbeat(progress, n, total)
            stored = InMemoryKeyframes(writer.read_keyframe, writer.poses, writer.timestamps_us)
            table = measure_place_repetition(stored, writer.global_descriptors, config, repetition_workers,
                                             lambda done, measured: repetition_beat(done == measured), show_progress)
            writer.set_place_repetition(table)
            if (message := unjudged_warning(table, n)) is not None:
                logger.warning("%s: %s", Path(out).name, message)
        if (message := motion_warning(writer.poses, writer.timestamps_us, config)) is not None:
            logger.warning("%s: %s", Path(out).name, message)
    except BaseException as exc:
        if writer is not None:
            writer.__exit__(type(exc), exc, exc.__traceback__)
        raise
    finally:
        bar.close()
    assert writer is not None
    writer.__exit__(None, None, None)
    logger.info("wrote map %s with %d keyframes", out, n)
    companion = far_view_path(out)
    if far_view is None:
        companion.unlink(missing_ok=True)
    else:
        far_extractor = extractor.with_view(far_view.cartesian)  # type: ignore[attr-defined]

        def far_progress(done: int, _n: int) -> None:
            if progress is not None:
                progress(n + done, total)  # after the map's n scan descriptions

        build_map(companion, far_extractor, load_scan, poses, radar_preset=radar_preset,
                  name=f"{name or Path(out).stem} (far view)", source=source, batch_size=batch_size,
                  max_keypoints=max_keypoints, overwrite=True, progress=None if progress is None else far_progress,
                  show_progress=show_progress,
                  place_repetition=place_repetition, localization=localization,
                  repetition_workers=repetition_workers, dense=far_view.dense,
                  pose_clock=None)  # the map's own build checked the same poses
    return Path(out)


def build_map_from_sequence(sequence_dir: str | Path, out: str | Path, extractor: FeatureExtractor, *,
                            layout: str | None = None, preset: str | None = None, min_spacing_m: float = 0.0,
                            time_unit: str | None = None, **kwargs: object) -> Path:
    """Build a map from a sequence folder in any supported layout (``reradar_core.io.datasets``).

    ``time_unit`` is the unit of the pose file's timestamps (``s``, ``ms``, ``us``, ``ns``) where they are not
    absolute UTC times (``load_sequence``'s ``pose_time_unit``); None: never guessed."""
    from reradar_core.io.datasets import load_sequence, pose_file_reader

    seq = load_sequence(sequence_dir, layout=layout, preset=preset, pose_time_unit=time_unit)
    keep = select_keyframes(seq.poses.poses, min_spacing_m)
    seq = seq.subset(keep)
    kwargs.setdefault("source", f"{seq.layout}:{Path(sequence_dir).resolve()}")
    track = seq.track if seq.track is not None and len(seq.track) else seq.poses
    kwargs.setdefault("pose_at", pose_file_reader(track, seq.preset))  # as the keyframe poses, NaN beyond the file
    kwargs.setdefault("name", seq.name)
    # keyframe poses at mid-sweep: what a registration against the keyframe's whole sweep aligns
    # (docs/CONVENTIONS.md)
    return build_map(out, extractor, seq.load_scan, seq.mid_sweep_poses(), radar_preset=seq.preset.name,
                     **kwargs)  # type: ignore[arg-type]
