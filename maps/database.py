"""A served map: the HDF5 keyframe store (``maps.store.KeyframeMap``) as the keyframe source of a core
``Localizer`` (``reradar_core.localization``), with the FAISS index over its global descriptors.

Global descriptors (N x D float32) live in the FAISS index; keypoints and local descriptors stay on disk and
are read (and cached, with their landmark grids) only for a query's candidates - or, with ``arrays_dir`` (the
service's default), are views into the map's memory-mapped arrays file (``maps.arrays``) shared by every
worker process.
"""

from __future__ import annotations

import functools
import hashlib
import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np

from maps.arrays import MapArrays
from maps.store import KeyframeMap, MapMetadata, open_map
from reradar_core.errors import ConfigError, MapFormatError
from reradar_core.features import ScanFeatures
from reradar_core.localization import (
    KeyframeSource,
    LocalizationConfig,
    LocalizationResult,
    Localizer,
    PosePrior,
    Retrieval,
    TwoViewResult,
)
from reradar_core.localization.far_view import FarViewConfig, far_fallback
from reradar_core.matching.dense import dense_image_settings
from reradar_core.retrieval import GlobalIndex, IndexConfig

__all__ = ["Retrieval", "MapDatabase", "far_view_mismatch", "FAR_VIEW"]

#: The far view a served map's companion is read with (geometry, sparse rule, dense registration): the defaults,
#: as ``reradar build-map --far-view`` writes them and the benchmark's ``+far`` / ``+dense`` rows use them.
FAR_VIEW = FarViewConfig()

logger = logging.getLogger(__name__)


def _return_freed_memory() -> None:
    """Hand the heap pages freed after indexing (the map's descriptor copy, FAISS' training buffers) back to
    the OS (glibc ``malloc_trim``), so resident memory is what the map keeps, not what opening it needed:
    measured with 100,000 keyframes in docs/BENCHMARKS.md. No-op elsewhere."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def far_view_mismatch(near: KeyframeSource, far: KeyframeSource,
                      presets: tuple[str, str] | None = None) -> str | None:
    """How the keyframes of ``far`` (a far-view companion, ``maps.paths.far_view_path``) differ from those of its
    map ``near``: another count, or another pose (x m, y m, yaw rad, compared exactly) or time (us) of a keyframe,
    as a companion built from other scans or poses has; with ``presets`` (the map's and the companion's
    ``radar_preset``), another radar preset too (its landmarks were read at another range-bin size); None when they
    are the same keyframes of the same radar."""
    if presets is not None and presets[0].lower() != presets[1].lower():  # map files may spell a preset in capitals
        return f"its scans are of radar preset {presets[1]!r}, the map's of {presets[0]!r}"
    if len(far) != len(near):
        return f"it holds {len(far)} keyframes, the map {len(near)}"
    for what, a, b in (("pose", near.poses, far.poses), ("time", near.timestamps_us, far.timestamps_us)):
        differ = np.flatnonzero(np.any(np.asarray(a).reshape(len(near), -1) != np.asarray(b).reshape(len(near), -1),
                                       axis=1))
        if differ.size:
            return (f"the {what} of {differ.size} of its {len(near)} keyframes differs from the map's (the first: "
                    f"keyframe {int(differ[0])})")
    return None


def _without_folder(exc: Exception, path: Path) -> str:
    """``exc``'s message with ``path`` named by its file name (the maps folder is the operator's, not the log's)."""
    return str(exc).replace(str(path), path.name)


class MapDatabase:
    """One keyframe map ready for queries.

    Attributes:
        map: the open ``KeyframeMap``; index: the ``GlobalIndex`` over its global descriptors;
        localizer: the ``Localizer`` reading keyframes from ``map``.
        repetition_stored: the map holds its place repetition (``/place_repetition``, written by ``build-map``).
        repetition_adopted: ... and it was measured under ``config``'s settings, so the localizer uses it (else
            each keyframe's is measured when it first wins).

    Args:
        keyframe_cache_size: keyframes whose features and compact screen data stay in memory between queries
            (LRU; ~50 KB each with 512 landmarks; None = all). Re-reading a keyframe and rebuilding its grids
            costs ~1.3 ms, as much as screening it, so a map that fits is best held whole.
        config: the localizer's default ``LocalizationConfig``.
        preload: read every keyframe at open (when the map fits in the cache) instead of on first use.
        arrays_dir: when given, the keyframes' features and screen masks are read from the map's shared arrays
            file in this folder (``maps.arrays``; built on first use), memory-mapped: every process serving the
            map shares those pages, and the cache holds only views into them.
    """

    def __init__(self, kf_map: KeyframeMap, index_config: IndexConfig = IndexConfig(),
                 keyframe_cache_size: int | None = 128, config: LocalizationConfig | None = None,
                 preload: bool = False, arrays_dir: str | Path | None = None) -> None:
        self.map = kf_map
        if kf_map.global_descriptors is None:
            raise ConfigError(f"{kf_map.path}: global descriptors were released; reopen the map")
        config = config or LocalizationConfig()
        self.arrays: MapArrays | None = None
        source: KeyframeSource = kf_map
        if arrays_dir is not None:  # keyframes as views into one memory-mapped file shared by every process
            try:
                self.arrays = MapArrays.open_or_build(kf_map, arrays_dir, config.alignment)
                source = self.arrays
            except OSError as exc:  # e.g. a read-only or full disk: serve from private memory instead
                logger.warning("%s: shared map arrays unavailable (%s); reading keyframes into this process",
                               kf_map.path.name, exc)
        self.index = GlobalIndex(kf_map.global_descriptors, index_config)
        kf_map.release_global_descriptors()  # the index holds its own copy
        _return_freed_memory()
        self.localizer = Localizer(self.index, source, config, cache_size=keyframe_cache_size, preload=preload)
        #: the far-view companion (``attach_far``): the same keyframes in ReRadar's far view, or None
        self.far: MapDatabase | None = None
        self._dense_warned: set[int] = set()  # keyframes whose unreadable dense image was logged
        self._far_dense = False  # ``far_dense``, decided when the companion is attached (it does not change)
        # the place repetition measured when the map was built: no query pays for measuring its winner's
        table = kf_map.place_repetition
        self.repetition_stored = table is not None
        self.repetition_adopted = table is not None and self.localizer.adopt_repetitions(table, config)
        if self.repetition_stored and not self.repetition_adopted and config.checks_place_repetition:
            logger.info("%s: the stored place repetition was measured under other localization settings; each "
                        "keyframe's is measured when it first wins (20-40 ms once per keyframe and process); "
                        "`reradar map-repetition` measures it again under the defaults", kf_map.path.name)
        elif not self.repetition_stored and config.checks_place_repetition:
            logger.info("%s: no stored place repetition (a map built before 2026-12-03 or with --no-place-repetition);"
                        " each keyframe's is measured when it first wins (20-40 ms once per keyframe and process); "
                        "`reradar map-repetition` stores it in the map", kf_map.path.name)

    @classmethod
    def open(cls, path: str | Path, model_id: str | None = None, weights_sha256: str | None = None,
             index_config: IndexConfig = IndexConfig(), **kwargs: object) -> MapDatabase:
        """Open the map at ``path`` (refusing another model's map when ``weights_sha256`` is given)."""
        return cls(open_map(path, model_id, weights_sha256), index_config, **kwargs)  # type: ignore[arg-type]

    @property
    def metadata(self) -> MapMetadata:
        return self.map.metadata

    @functools.cached_property
    def version(self) -> str:
        """A fingerprint of this map's keyframes (poses, times) and creation time (16 hex digits): another map
        registered under the same id has another one, so what is kept per map between requests (tracking
        sessions: a pose in this map's frame) is kept per version. Stays readable after the map is closed."""
        digest = hashlib.sha256()
        digest.update(np.ascontiguousarray(self.map.poses, np.float64).tobytes())
        digest.update(np.ascontiguousarray(self.map.timestamps_us, np.int64).tobytes())
        digest.update(self.metadata.created_utc.encode())
        return digest.hexdigest()[:16]

    def __len__(self) -> int:
        return len(self.map)

    def retrieve(self, global_descriptor: np.ndarray, k: int) -> list[Retrieval]:
        """Top-``k`` keyframes by global descriptor, best first."""
        return self.localizer.retrieve(global_descriptor, k)

    def localize(self, query: ScanFeatures, config: LocalizationConfig | None = None) -> LocalizationResult:
        """``Localizer.localize`` on this map."""
        return self.localizer.localize(query, config)

    def attach_far(self, far: MapDatabase) -> None:
        """Serve ``far`` (the far-view companion, ``maps.paths.far_view_path``) for the answers this map refuses.

        Raises:
            MapFormatError: ``far`` does not hold this map's keyframes (another count, poses or times: a companion
                left from another map); ``far`` is not attached.
        """
        problem = far_view_mismatch(self.localizer.keyframes, far.localizer.keyframes,
                                    (self.metadata.radar_preset, far.metadata.radar_preset))
        if problem is not None:
            raise MapFormatError(f"{far.map.path.name} does not hold the keyframes of {self.map.path.name} ({problem}); "
                                 "rebuild it with `reradar build-map --far-view`")
        self.far = far
        self._far_dense = far.map.dense_settings == dense_image_settings(FAR_VIEW.dense)
        if self._far_dense and len(far.map):
            try:  # a companion that declares dense images but holds none (or not the first) is served without them
                far.map.read_dense_image(0)
            except MapFormatError as exc:
                self._far_dense = False
                logger.warning("%s declares dense images but keyframe 0's is unreadable (%s); its far view is served "
                               "without the dense registration (rebuild it with `reradar build-map --far-view`)",
                               far.map.path.name, _without_folder(exc, far.map.path))

    def localize_views(self, query: ScanFeatures, far_features: Callable[[], ScanFeatures] | None,
                       config: LocalizationConfig | None = None,
                       dense_query: Callable[[], np.ndarray] | None = None) -> TwoViewResult:
        """``localize``, and when refused, again in the far view (``far_fallback``, as ``localize_two_views``) if this
        map has a far companion and ``far_features`` computes the query's far-view features (only called then);
        when the far view refuses too, its dense registration if the companion holds dense images made as
        ``FAR_VIEW.dense`` makes them and ``dense_query`` computes the query's (only called then)."""
        return far_fallback(self.localize(query, config), self.localizer, query, self._far_localizer, far_features,
                            config, FAR_VIEW, *self._dense(dense_query))

    def track_views(self, query: ScanFeatures, prior: PosePrior, far_features: Callable[[], ScanFeatures] | None,
                    config: LocalizationConfig | None = None,
                    dense_query: Callable[[], np.ndarray] | None = None) -> TwoViewResult:
        """``track``, and when that ends in a refused global answer (no consistent pose near the prior, or a prior
        too loose to track from), the far view as in ``localize_views``; a refused tracked answer stands."""
        result = self.track(query, prior, config)
        if result.mode != "global":
            return TwoViewResult(result, "near", result)
        return far_fallback(result, self.localizer, query, self._far_localizer, far_features, config, FAR_VIEW,
                            *self._dense(dense_query))

    @property
    def _far_localizer(self) -> Localizer | None:
        return self.far.localizer if self.far is not None else None

    @property
    def far_dense(self) -> bool:
        """The far-view companion holds every keyframe's dense image, made with the settings this process makes
        the query's with (``FAR_VIEW.dense``): its dense registration can run."""
        return self.far is not None and self._far_dense

    def _dense(self, dense_query: Callable[[], np.ndarray] | None
               ) -> tuple[Callable[[], np.ndarray] | None, Callable[[int], np.ndarray] | None]:
        """(``dense_query``, the companion's keyframe image reader) when dense registration can run, else Nones."""
        if dense_query is None or not self.far_dense:
            return None, None
        assert self.far is not None
        far_map = self.far.map

        def keyframe_image(keyframe_id: int) -> np.ndarray:
            # a damaged image is the served file's fault, not the request's: that candidate aligns with nothing
            # (an all-zero image correlates 0 at every pose), so the answer is at worst the far view's refusal
            try:
                return far_map.read_dense_image(keyframe_id)
            except MapFormatError as exc:
                if keyframe_id not in self._dense_warned:  # once per keyframe, not on every request
                    self._dense_warned.add(keyframe_id)
                    logger.warning("%s: dense image of keyframe %d unreadable (%s); not registered against",
                                   far_map.path.name, keyframe_id, _without_folder(exc, far_map.path))
                w = far_map.metadata.cartesian_width_px
                return np.zeros((w, w), np.float32)
        return dense_query, keyframe_image

    def track(self, query: ScanFeatures, prior: PosePrior,
              config: LocalizationConfig | None = None) -> LocalizationResult:
        """``Localizer.track`` on this map (tracking mode, global fallback)."""
        return self.localizer.track(query, prior, config)

    def close(self) -> None:
        if self.far is not None:
            self.far.close()
        self.localizer.clear()
        if self.arrays is not None:
            self.arrays.close()
        self.map.close()
