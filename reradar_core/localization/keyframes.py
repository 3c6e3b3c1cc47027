"""Where a ``Localizer`` reads map keyframes from, and the per-keyframe cache of features + landmark grids.

A keyframe source is anything with ``poses`` (N, 3), ``timestamps_us`` (N,), ``len()`` and
``read_keyframe(i) -> ScanFeatures``: the HDF5 map (``maps.store.KeyframeMap``) in the service, an
in-memory list (``InMemoryKeyframes``) in the benchmark and tests. A source may also offer
``read_screen(i, alignment_config) -> ScreenKeyframe | None`` (precomputed screen data, e.g. the service's
memory-mapped ``maps.arrays.MapArrays``); the cache then uses it instead of building the alignment mask.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.se2 import check_poses, check_yaw_radians
from reradar_core.localization.screening import ScreenKeyframe, screen_keyframe
from reradar_core.matching import AlignmentConfig, LandmarkGrid, build_landmark_grid

__all__ = ["KeyframeSource", "InMemoryKeyframes", "KeyframeCache", "CachedKeyframe", "select_keyframes"]


def select_keyframes(poses: np.ndarray, min_spacing_m: float) -> np.ndarray:
    """Indices of scans kept as keyframes: the first, then each scan >= ``min_spacing_m`` (metres) from the
    last kept one. ``min_spacing_m <= 0`` keeps every scan. ``poses`` (N, 3) (x m, y m, yaw rad).

    ``reradar build-map --min-spacing-m`` (``maps.build``) and the confidence fit's sparser maps
    (``confidence_fit.split_runs``) both use it."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.size == 0:
        return np.arange(0)
    poses = check_poses(poses, "poses")  # (N, 2) positions reshaped to (N, 3) would interleave into other places
    if min_spacing_m <= 0:
        return np.arange(len(poses))
    keep = [0]
    for i in range(1, len(poses)):
        if np.hypot(*(poses[i, :2] - poses[keep[-1], :2])) >= min_spacing_m:
            keep.append(i)
    return np.asarray(keep, dtype=np.int64)


@runtime_checkable
class KeyframeSource(Protocol):
    """A map's keyframes.

    Attributes:
        poses: (N, 3) float64 ``T_map_keyframe`` (x m, y m, yaw rad), map frame.
        timestamps_us: (N,) int64 keyframe timestamps, microseconds.
    """

    poses: np.ndarray
    timestamps_us: np.ndarray

    def __len__(self) -> int: ...

    def read_keyframe(self, index: int) -> ScanFeatures: ...


class InMemoryKeyframes:
    """A ``KeyframeSource`` over features held in memory (or produced on demand by ``features_of``).

    Args:
        features: the keyframes' features, or a callable index -> features (read lazily, e.g. from a cache).
        poses: (N, 3) float64 ``T_map_keyframe``.
        timestamps_us: (N,) int64; default: each keyframe's ``ScanFeatures.timestamp_us`` when ``features``
            is a sequence, else zeros.
    """

    def __init__(self, features: Sequence[ScanFeatures] | Callable[[int], ScanFeatures], poses: np.ndarray,
                 timestamps_us: np.ndarray | None = None) -> None:
        self.poses = check_poses(poses, "keyframe poses")
        check_yaw_radians(self.poses, "keyframe poses")
        if callable(features):
            self._read = features
        else:
            items = list(features)
            if len(items) != len(self.poses):
                raise ConfigError(f"{len(items)} keyframe features for {len(self.poses)} poses")
            self._read = items.__getitem__
            if timestamps_us is None:
                timestamps_us = np.array([f.timestamp_us for f in items], np.int64)
        self.timestamps_us = (np.zeros(len(self.poses), np.int64) if timestamps_us is None
                              else np.asarray(timestamps_us, np.int64).reshape(-1))
        if len(self.timestamps_us) != len(self.poses):
            raise ConfigError(f"{len(self.timestamps_us)} keyframe timestamps for {len(self.poses)} poses")

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    def read_keyframe(self, index: int) -> ScanFeatures:
        if not 0 <= index < len(self):
            raise IndexError(f"keyframe {index} out of range [0, {len(self)})")
        return self._read(index)


class CachedKeyframe:
    """One keyframe prepared for localization: its features and its compact screen data (``ScreenKeyframe``:
    the features' own arrays and a bit-packed alignment mask; ~30 KB in all with 512 landmarks)."""

    __slots__ = ("features", "screen")

    def __init__(self, features: ScanFeatures, config: AlignmentConfig, screen: ScreenKeyframe | None = None) -> None:
        self.features = features
        self.screen = screen if screen is not None else screen_keyframe(features.keypoints_xy_m,
                                                                          features.local_descriptors, config)


class KeyframeCache:
    """Thread-safe caches over a ``KeyframeSource``: ``CachedKeyframe`` s (screen data) and, separately and
    smaller, the landmark grids + KD-trees (``LandmarkGrid``) the full pose estimate uses: made from the
    screen's alignment mask (``LandmarkGrid.from_within_mask``, ~0.1 MB with 512 landmarks), not a float
    distance transform.

    Reading a keyframe from HDF5 and building its grids costs ~1.3 ms while screening it costs ~1 ms, so a
    map whose screen data fits in memory (~50 KB per keyframe with 512 landmarks, measured) is best held whole
    (``preload``); only the few verified candidates per query need the larger grid.

    Args:
        source: the keyframes.
        config: alignment settings (grid cell and score threshold of the screen masks).
        max_cached: keyframes whose screen data is kept (least recently used dropped first); None = all.
        max_grids: landmark grids kept (LRU).
    """

    def __init__(self, source: KeyframeSource, config: AlignmentConfig, max_cached: int | None = None,
                 max_grids: int = 64) -> None:
        if (max_cached is not None and max_cached < 1) or max_grids < 1:
            raise ConfigError(f"max_cached must be >= 1 or None and max_grids >= 1, got {max_cached}, {max_grids}")
        self.source = source
        self.config = config
        self.max_cached = max_cached
        self.max_grids = max_grids
        self._items: OrderedDict[int, CachedKeyframe] = OrderedDict()
        self._grids: OrderedDict[int, LandmarkGrid] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._items)

    @staticmethod
    def _lru_get(store: OrderedDict, key: int) -> object | None:
        item = store.get(key)
        if item is not None:
            store.move_to_end(key)
        return item

    @staticmethod
    def _lru_put(store: OrderedDict, key: int, item: object, limit: int | None) -> None:
        store[key] = item
        if limit is not None:
            while len(store) > limit:
                store.popitem(last=False)

    def get(self, keyframe_id: int) -> CachedKeyframe:
        """The keyframe's features and screen data, read and built on first use."""
        with self._lock:
            item = self._lru_get(self._items, keyframe_id)
        if item is not None:
            return item  # type: ignore[return-value]
        # outside the lock: slow. A source with precomputed screen data (``maps.arrays.MapArrays``: views into
        # a memory-mapped file shared by worker processes) hands it over; else it is built here
        read_screen = getattr(self.source, "read_screen", None)
        screen = read_screen(keyframe_id, self.config) if read_screen is not None else None
        built = CachedKeyframe(self.source.read_keyframe(keyframe_id), self.config, screen)
        with self._lock:
            self._lru_put(self._items, keyframe_id, built, self.max_cached)
        return built

    def landmark_grid(self, keyframe_id: int) -> LandmarkGrid:
        """The keyframe's ``LandmarkGrid`` (alignment mask at the score threshold + KD-tree) for the full pose
        estimate and tracking."""
        with self._lock:
            grid = self._lru_get(self._grids, keyframe_id)
        if grid is not None:
            return grid  # type: ignore[return-value]
        item = self.get(keyframe_id)
        # the screen's alignment mask is the full grid's mask at the score threshold (same cells), which is all
        # the pose estimate's scoring reads: no distance transform, ~0.1 MB instead of ~0.6 MB per grid
        sg = item.screen.grid
        if sg.cell_m == self.config.grid_cell_m:
            built = LandmarkGrid.from_within_mask(sg.packed, sg.n, sg.origin_m, sg.cell_m,
                                                  self.config.score_threshold_m, item.features.keypoints_xy_m)
        else:
            built = build_landmark_grid(item.features.keypoints_xy_m, self.config.grid_cell_m)
        with self._lock:
            self._lru_put(self._grids, keyframe_id, built, self.max_grids)
        return built

    def preload(self) -> bool:
        """Read every keyframe when the whole map fits in the cache, so no query pays for a cold read;
        returns whether it did (a larger map fills the LRU as it is queried)."""
        if self.max_cached is not None and len(self.source) > self.max_cached:
            return False
        for i in range(len(self.source)):
            self.get(i)
        return True

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._grids.clear()
