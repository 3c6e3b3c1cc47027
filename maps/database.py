"""A served map: the HDF5 keyframe store (``maps.store.KeyframeMap``) as the keyframe source of a core
``Localizer`` (``reradar_core.localization``), with the FAISS index over its global descriptors.

Global descriptors (N x D float32) live in the FAISS index; keypoints and local descriptors stay on disk and
are read (and cached, with their landmark grids) only for a query's candidates.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from maps.store import KeyframeMap, MapMetadata, open_map
from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.localization import LocalizationConfig, LocalizationResult, Localizer, PosePrior, Retrieval
from reradar_core.retrieval import GlobalIndex, IndexConfig

__all__ = ["Retrieval", "MapDatabase"]


def _return_freed_memory() -> None:
    """Hand the heap pages freed after indexing (the map's descriptor copy, FAISS' training buffers) back to
    the OS (glibc ``malloc_trim``), so resident memory is what the map keeps, not what opening it needed:
    measured with 100,000 keyframes in docs/BENCHMARKS.md. No-op elsewhere."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


class MapDatabase:
    """One keyframe map ready for queries.

    Attributes:
        map: the open ``KeyframeMap``; index: the ``GlobalIndex`` over its global descriptors;
        localizer: the ``Localizer`` reading keyframes from ``map``.

    Args:
        keyframe_cache_size: keyframes whose features and compact screen data stay in memory between queries
            (LRU; ~50 KB each with 512 landmarks; None = all). Re-reading a keyframe and rebuilding its grids
            costs ~1.3 ms, as much as screening it, so a map that fits is best held whole.
        config: the localizer's default ``LocalizationConfig``.
        preload: read every keyframe at open (when the map fits in the cache) instead of on first use.
    """

    def __init__(self, kf_map: KeyframeMap, index_config: IndexConfig = IndexConfig(),
                 keyframe_cache_size: int | None = 128, config: LocalizationConfig | None = None,
                 preload: bool = False) -> None:
        self.map = kf_map
        if kf_map.global_descriptors is None:
            raise ConfigError(f"{kf_map.path}: global descriptors were released; reopen the map")
        self.index = GlobalIndex(kf_map.global_descriptors, index_config)
        kf_map.release_global_descriptors()  # the index holds its own copy
        _return_freed_memory()
        self.localizer = Localizer(self.index, kf_map, config, cache_size=keyframe_cache_size, preload=preload)

    @classmethod
    def open(cls, path: str | Path, model_id: str | None = None, weights_sha256: str | None = None,
             index_config: IndexConfig = IndexConfig(), **kwargs: object) -> MapDatabase:
        """Open the map at ``path`` (refusing another model's map when ``weights_sha256`` is given)."""
        return cls(open_map(path, model_id, weights_sha256), index_config, **kwargs)  # type: ignore[arg-type]

    @property
    def metadata(self) -> MapMetadata:
        return self.map.metadata

    def __len__(self) -> int:
        return len(self.map)

    def retrieve(self, global_descriptor: np.ndarray, k: int) -> list[Retrieval]:
        """Top-``k`` keyframes by global descriptor, best first."""
        return self.localizer.retrieve(global_descriptor, k)

    def localize(self, query: ScanFeatures, config: LocalizationConfig | None = None) -> LocalizationResult:
        """``Localizer.localize`` on this map."""
        return self.localizer.localize(query, config)

    def track(self, query: ScanFeatures, prior: PosePrior,
              config: LocalizationConfig | None = None) -> LocalizationResult:
        """``Localizer.track`` on this map (tracking mode, global fallback)."""
        return self.localizer.track(query, prior, config)

    def close(self) -> None:
        self.localizer.clear()
        self.map.close()
