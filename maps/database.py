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
from reradar_core.localization import LocalizationConfig, LocalizationResult, Localizer, Retrieval
from reradar_core.retrieval import GlobalIndex, IndexConfig

__all__ = ["Retrieval", "MapDatabase"]


class MapDatabase:
    """One keyframe map ready for queries.

    Attributes:
        map: the open ``KeyframeMap``; index: the ``GlobalIndex`` over its global descriptors;
        localizer: the ``Localizer`` reading keyframes from ``map``.

    Args:
        keyframe_cache_size: keyframes whose features and landmark distance grid stay in memory between
            queries (LRU; about 0.33 MB each; None = all). Re-reading a keyframe and rebuilding its grid costs
            ~1.3 ms, and with 20 candidates per query that is most of the verification time on a revisited
            route.
        config: the localizer's default ``LocalizationConfig``.
    """

    def __init__(self, kf_map: KeyframeMap, index_config: IndexConfig = IndexConfig(),
                 keyframe_cache_size: int | None = 128, config: LocalizationConfig | None = None) -> None:
        self.map = kf_map
        if kf_map.global_descriptors is None:
            raise ConfigError(f"{kf_map.path}: global descriptors were released; reopen the map")
        self.index = GlobalIndex(kf_map.global_descriptors, index_config)
        kf_map.release_global_descriptors()  # the index holds its own copy
        self.localizer = Localizer(self.index, kf_map, config, cache_size=keyframe_cache_size)

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

    def close(self) -> None:
        self.localizer.clear()
        self.map.close()
