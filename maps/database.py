"""A loaded map: the HDF5 keyframe store plus its FAISS index, with retrieval and localization.

Global descriptors (N x D float32) live in the FAISS index; keypoints and local descriptors stay on disk and
are read only for a query's top-k candidates.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from maps.index import GlobalIndex, IndexConfig, similarity_to_distance
from maps.store import KeyframeMap, MapMetadata, open_map
from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.localization import (
    Candidate,
    KeyframeCandidates,
    LocalizationConfig,
    LocalizationResult,
    localize,
)
from reradar_core.matching import AlignmentConfig, LandmarkGrid

__all__ = ["Retrieval", "MapDatabase"]


@dataclass(frozen=True)
class Retrieval:
    """One retrieved keyframe: id, timestamp (us), map pose (x m, y m, yaw rad), descriptor distance."""

    keyframe_id: int
    timestamp_us: int
    T_map_keyframe: np.ndarray
    descriptor_distance: float
    rank: int


class MapDatabase:
    """Retrieval and localization against one keyframe map.

    Attributes:
        map: the open ``KeyframeMap``; index: the ``GlobalIndex`` over its global descriptors.

    Args:
        keyframe_cache_size: keyframes whose features and landmark distance grid stay in memory between
            queries (LRU; about 0.33 MB each). Re-reading a keyframe and rebuilding its grid costs ~2 ms, and
            with 20 candidates per query that is most of the verification time on a revisited route.
    """

    def __init__(self, kf_map: KeyframeMap, index_config: IndexConfig = IndexConfig(),
                 keyframe_cache_size: int = 128) -> None:
        self.map = kf_map
        self._keyframes = KeyframeCandidates(kf_map.read_keyframe, AlignmentConfig().grid_cell_m,
                                             max_cached=keyframe_cache_size)
        if kf_map.global_descriptors is None:
            raise ConfigError(f"{kf_map.path}: global descriptors were released; reopen the map")
        self.index = GlobalIndex(kf_map.global_descriptors, index_config)
        kf_map.release_global_descriptors()  # the index holds its own copy

    @classmethod
    def open(cls, path: str | Path, model_id: str | None = None, weights_sha256: str | None = None,
             index_config: IndexConfig = IndexConfig()) -> MapDatabase:
        """Open the map at ``path`` (refusing another model's map when ``weights_sha256`` is given)."""
        return cls(open_map(path, model_id, weights_sha256), index_config)

    @property
    def metadata(self) -> MapMetadata:
        return self.map.metadata

    def __len__(self) -> int:
        return len(self.map)

    def retrieve(self, global_descriptor: np.ndarray, k: int) -> list[Retrieval]:
        """Top-``k`` keyframes by global descriptor, best first."""
        g = np.asarray(global_descriptor, np.float32).reshape(-1)
        if g.shape[0] != self.index.dim:
            raise ConfigError(
                f"query descriptor has {g.shape[0]} values but map {self.map.path.name} stores {self.index.dim}"
            )
        idx, sims = self.index.search(g, k)
        dists = similarity_to_distance(sims[0])
        out = []
        for rank, (i, d) in enumerate(zip(idx[0], dists, strict=True)):
            if i < 0:
                continue
            out.append(Retrieval(int(i), int(self.map.timestamps_us[i]), self.map.poses[i].copy(), float(d), rank))
        return out

    def localize(self, query: ScanFeatures,
                 config: LocalizationConfig | None = None) -> tuple[list[Retrieval], LocalizationResult]:
        """Retrieve ``config.num_to_retrieve`` candidates, screen / verify them and return (the retrievals that
        were screened, result).

        ``result.timings_ms`` gains ``retrieve_ms`` (FAISS search) and ``read_ms`` (keyframe reads from disk and
        landmark grids, both cached per keyframe).
        """
        config = config or LocalizationConfig()
        t0 = time.perf_counter()
        retrievals = self.retrieve(query.global_descriptor, config.num_to_retrieve)
        t1 = time.perf_counter()
        wanted = retrievals if config.rerank else retrievals[:1]
        read_s = [0.0]

        def loader(keyframe_id: int):  # features + grid from the LRU cache, read on first use only
            def load() -> tuple[ScanFeatures, LandmarkGrid]:
                t = time.perf_counter()
                out = self._keyframes.load(keyframe_id)
                read_s[0] += time.perf_counter() - t
                return out
            return load

        candidates = [Candidate(r.keyframe_id, r.T_map_keyframe, None, r.descriptor_distance, r.rank,
                                loader=loader(r.keyframe_id)) for r in wanted]
        result = localize(query, candidates, config)
        result.timings_ms["retrieve_ms"] = (t1 - t0) * 1e3
        result.timings_ms["read_ms"] = read_s[0] * 1e3
        return retrievals[: max(len(result.candidates), 1)], result

    def close(self) -> None:
        self._keyframes.clear()
        self.map.close()
