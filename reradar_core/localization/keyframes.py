"""Where a ``Localizer`` reads map keyframes from, and the per-keyframe cache of features + landmark grids.

A keyframe source is anything with ``poses`` (N, 3), ``timestamps_us`` (N,), ``len()`` and
``read_keyframe(i) -> ScanFeatures``: the HDF5 map (``maps.store.KeyframeMap``) in the service, an
in-memory list (``InMemoryKeyframes``) in the benchmark and tests.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.matching import LandmarkGrid, build_landmark_grid

__all__ = ["KeyframeSource", "InMemoryKeyframes", "KeyframeCache", "CachedKeyframe"]


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
        self.poses = np.asarray(poses, np.float64).reshape(-1, 3)
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

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    def read_keyframe(self, index: int) -> ScanFeatures:
        if not 0 <= index < len(self):
            raise IndexError(f"keyframe {index} out of range [0, {len(self)})")
        return self._read(index)


class CachedKeyframe:
    """One keyframe prepared for alignment: its features and its landmark distance grid (built once)."""

    __slots__ = ("features", "grid")

    def __init__(self, features: ScanFeatures, grid: LandmarkGrid) -> None:
        self.features = features
        self.grid = grid


class KeyframeCache:
    """Thread-safe LRU of ``CachedKeyframe`` s read from a ``KeyframeSource``.

    Reading a keyframe from HDF5 and building its landmark grid costs ~1.3 ms; a query screens 20-60
    candidates, so keeping them between queries is most of the difference between a cold and a warm map.

    Args:
        source: the keyframes.
        grid_cell_m: cell of the landmark grids (``AlignmentConfig.grid_cell_m``).
        max_cached: keyframes kept (least recently used dropped first); None = all.
    """

    def __init__(self, source: KeyframeSource, grid_cell_m: float, max_cached: int | None = None) -> None:
        if max_cached is not None and max_cached < 1:
            raise ConfigError(f"max_cached must be >= 1 or None, got {max_cached}")
        self.source = source
        self.grid_cell_m = grid_cell_m
        self.max_cached = max_cached
        self._items: OrderedDict[int, CachedKeyframe] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._items)

    def get(self, keyframe_id: int) -> CachedKeyframe:
        """The keyframe's features and grid, read and built on first use."""
        with self._lock:
            item = self._items.get(keyframe_id)
            if item is not None:
                self._items.move_to_end(keyframe_id)
                return item
        features = self.source.read_keyframe(keyframe_id)  # outside the lock: reads may be slow
        item = CachedKeyframe(features, build_landmark_grid(features.keypoints_xy_m, self.grid_cell_m))
        with self._lock:
            self._items[keyframe_id] = item
            if self.max_cached is not None:
                while len(self._items) > self.max_cached:
                    self._items.popitem(last=False)
        return item

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
