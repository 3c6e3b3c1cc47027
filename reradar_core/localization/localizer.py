"""``Localizer``: the product's one operation, retrieve -> screen -> verify, over one map.

The service (``maps.database.MapDatabase``), the benchmark's ``Ours`` and the stage timings all call it, so
every number the benchmark reports is measured on the service's code path.

    localizer = Localizer(GlobalIndex(global_descriptors), keyframes, LocalizationConfig())
    result = localizer.localize(features)            # global localization
    result.T_map_query, result.alignment_score, result.candidates
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.localization.keyframes import KeyframeCache, KeyframeSource
from reradar_core.localization.pipeline import (
    Candidate,
    LocalizationConfig,
    LocalizationResult,
    localize,
)
from reradar_core.matching import LandmarkGrid
from reradar_core.retrieval import GlobalIndex, similarity_to_distance

__all__ = ["Localizer", "Retrieval"]


@dataclass(frozen=True)
class Retrieval:
    """One retrieved keyframe: id, timestamp (us), map pose ``T_map_keyframe`` (x m, y m, yaw rad), Euclidean
    distance between unit global descriptors in [0, 2], 0-based rank."""

    keyframe_id: int
    timestamp_us: int
    T_map_keyframe: np.ndarray
    descriptor_distance: float
    rank: int


class Localizer:
    """Global localization of one scan's features on one map.

    Args:
        index: ``GlobalIndex`` over the keyframes' (N, D) unit global descriptors (row i = keyframe i).
        keyframes: the keyframes' poses, timestamps and features (``KeyframeSource``).
        config: default settings of ``localize`` (a call may pass its own).
        cache_size: keyframes whose features and landmark grid stay in memory between queries (LRU);
            None = the whole map.
    """

    def __init__(self, index: GlobalIndex, keyframes: KeyframeSource,
                 config: LocalizationConfig | None = None, cache_size: int | None = None) -> None:
        if index.size != len(keyframes):
            raise ConfigError(f"index holds {index.size} descriptors but the map has {len(keyframes)} keyframes")
        self.index = index
        self.keyframes = keyframes
        self.config = config or LocalizationConfig()
        self.cache = KeyframeCache(keyframes, self.config.alignment.grid_cell_m, max_cached=cache_size)

    def __len__(self) -> int:
        return len(self.keyframes)

    def retrieve(self, global_descriptor: np.ndarray, k: int) -> list[Retrieval]:
        """Top-``k`` keyframes by global descriptor, best first.

        Raises:
            ConfigError: the descriptor's length differs from the map's D.
        """
        g = np.asarray(global_descriptor, np.float32).reshape(-1)
        if g.shape[0] != self.index.dim:
            raise ConfigError(f"query descriptor has {g.shape[0]} values but the map stores {self.index.dim}")
        idx, sims = self.index.search(g, k)
        dists = similarity_to_distance(sims[0])
        poses, ts = self.keyframes.poses, self.keyframes.timestamps_us
        return [Retrieval(int(i), int(ts[i]), poses[i].copy(), float(d), rank)
                for rank, (i, d) in enumerate(zip(idx[0], dists, strict=True)) if i >= 0]

    def localize(self, features: ScanFeatures, config: LocalizationConfig | None = None) -> LocalizationResult:
        """Retrieve ``config.num_to_retrieve`` candidates, screen and verify them (``localization.localize``).

        Returns:
            ``LocalizationResult``; ``timings_ms`` gains ``retrieve_ms`` (FAISS search) and ``read_ms``
            (keyframe reads and landmark grids, cached per keyframe).
        """
        config = config or self.config
        t0 = time.perf_counter()
        hits = self.retrieve(features.global_descriptor, config.num_to_retrieve)
        t1 = time.perf_counter()
        read_s = [0.0]

        def loader(keyframe_id: int):  # features + grid from the cache, read on first use only
            def load() -> tuple[ScanFeatures, LandmarkGrid]:
                t = time.perf_counter()
                item = self.cache.get(keyframe_id)
                read_s[0] += time.perf_counter() - t
                return item.features, item.grid
            return load

        wanted = hits if config.rerank else hits[:1]
        candidates = [Candidate(h.keyframe_id, h.T_map_keyframe, None, h.descriptor_distance, h.rank,
                                loader=loader(h.keyframe_id)) for h in wanted]
        result = localize(features, candidates, config)
        result.timings_ms["retrieve_ms"] = (t1 - t0) * 1e3
        result.timings_ms["read_ms"] = read_s[0] * 1e3
        return result

    def clear(self) -> None:
        """Drop the cached keyframes."""
        self.cache.clear()
