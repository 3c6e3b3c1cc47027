"""Everything the routes share, created in the app's lifespan handler (never at import)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from maps.database import FAR_VIEW
from reradar_core.errors import ReRadarError, ScanFormatError
from reradar_core.features import ScanFeatures
from reradar_core.io.presets import get_preset
from reradar_core.io.scan import (
    NpyLayout,
    RadarScan,
    load_scan_bytes,
    range_bins_ambiguous,
    same_range_geometry,
)
from reradar_core.localization import LocalizationConfig
from reradar_core.localization.extractor import FeatureExtractor
from reradar_core.matching.dense import dense_image
from service.core.config import Settings
from service.core.errors import ServiceError
from service.core.metrics import Metrics
from service.core.registry import MapRegistry
from service.core.scan_cache import ScanCache
from service.core.sessions import SessionConfig, SessionStore

__all__ = ["ServiceState"]


@dataclass
class ServiceState:
    """Loaded model, maps, scan cache and metrics of one running service."""

    settings: Settings
    extractor: FeatureExtractor
    registry: MapRegistry
    cache: ScanCache
    metrics: Metrics
    sessions: SessionStore = field(init=False)

    def __post_init__(self) -> None:
        self.sessions = SessionStore(SessionConfig(max_sessions=self.settings.max_sessions,
                                                   ttl_s=self.settings.session_ttl_s))

    def localization_config(self, top_k: int | None = None) -> LocalizationConfig:
        """The configured ``LocalizationConfig``, with a request's ``top_k`` when given."""
        config = self.settings.localization
        return replace(config, top_k=top_k) if top_k else config

    def map_preset(self, map_id: str | None) -> str | None:
        """The radar preset recorded in map ``map_id`` (None: no such map, or it is not ready)."""
        if not map_id:
            return None
        try:
            return self.registry.ready(map_id).metadata.radar_preset
        except ServiceError:  # unknown / building map: the route answers that after the upload is read
            return None

    def describe_upload(self, data: bytes, filename: str, preset: str | None, timings_ms: dict[str, float],
                        scan_layout: NpyLayout = "polar", map_id: str | None = None,
                        ) -> tuple[ScanFeatures, str | None, bool, RadarScan]:
        """Decode an uploaded scan (PNG / .npy, an .npy as ``scan_layout``) and compute its features; adds
        ``decode_ms``/``extract_ms``. Without ``preset``, the geometry of the ready map ``map_id`` is used where
        the scan fits it (``load_scan_bytes``'s ``map_preset``).

        Returns:
            The features, the scan's preset, whether that preset was left open: none was given and the scan
            does not fix one (a polar .npy carries no geometry; 3,360 range bins fit presets of different bin
            size), so it is ``map_id``'s or a guess (``check_cached_preset`` refuses such a scan on a map of
            another range geometry), and the decoded scan (``far_features_of``).

        Raises:
            ScanFormatError: empty, corrupt or wrongly shaped scans, non-finite features.
        """
        if not data:
            raise ScanFormatError("the uploaded scan file is empty")
        t0 = time.perf_counter()
        # the sides were checked on the upload's header (``scan_input.check_scan_upload``, every caller's path)
        map_preset = self.map_preset(map_id)
        scan = load_scan_bytes(data, filename or "scan.png", preset, scan_layout, map_preset)
        polar_npy = (filename or "").lower().endswith(".npy") and scan_layout == "polar"
        preset_open = preset is None and (polar_npy or range_bins_ambiguous(scan.num_range_bins))
        t1 = time.perf_counter()
        try:
            features = self.extractor.describe(scan)
        except (ValueError, RuntimeError, IndexError, FloatingPointError) as exc:
            # shape/size problems surface as errors inside the network; they are input errors
            raise ScanFormatError(f"could not compute features for this scan ({exc})") from exc
        t2 = time.perf_counter()
        if not np.all(np.isfinite(features.global_descriptor)):
            raise ScanFormatError("the scan produced a non-finite descriptor (empty or saturated scan?)")
        timings_ms["decode_ms"] = (t1 - t0) * 1e3
        timings_ms["extract_ms"] = (t2 - t1) * 1e3
        return features, scan.preset, preset_open, scan

    def far_features_of(self, scan: RadarScan, timings_ms: dict[str, float]) -> Callable[[], ScanFeatures] | None:
        """Computes ``scan``'s far-view features when called (``MapDatabase.localize_views`` calls it only for a
        refused answer on a map with a far-view companion), adding ``far_extract_ms``; None without a far view."""
        far = self.registry.far_extractor
        if far is None:
            return None

        def compute() -> ScanFeatures:
            t0 = time.perf_counter()
            try:
                return far.describe(scan)
            finally:
                timings_ms["far_extract_ms"] = (time.perf_counter() - t0) * 1e3
        return compute

    def dense_image_of(self, scan: RadarScan, timings_ms: dict[str, float]) -> Callable[[], np.ndarray] | None:
        """Computes ``scan``'s far-view dense image when called (``MapDatabase.localize_views`` calls it only when
        both views refused on a map whose far-view companion holds dense images), adding ``dense_image_ms``; None
        without a far view. Inline scans only: a cached ``scan_id`` keeps no scan to make it from."""
        if self.registry.far_extractor is None:
            return None

        def compute() -> np.ndarray:
            t0 = time.perf_counter()
            try:
                # rounded as a map and the scan cache store images (float16): inline and by scan_id, one answer
                return dense_image(scan, FAR_VIEW.cartesian, FAR_VIEW.dense).astype(np.float16).astype(np.float32)
            finally:
                timings_ms["dense_image_ms"] = (time.perf_counter() - t0) * 1e3
        return compute

    def check_cached_preset(self, scan_id: str, preset: str | None, preset_open: bool, map_id: str) -> None:
        """Refuse a cached scan whose preset the client left open (``describe_upload``: a guess, or the map's its
        upload named) on a map of another range geometry: its features were computed with bins of another length,
        which no later step can undo.

        Raises:
            ScanFormatError (422): what was assumed, what the map holds, and how to upload the scan again.
        """
        map_preset = self.map_preset(map_id)
        if not preset_open or preset is None or map_preset is None or map_preset == preset:
            return
        try:
            if same_range_geometry(preset, map_preset):
                return
            ours, theirs = get_preset(preset), get_preset(map_preset)
        except ReRadarError:  # a map of a preset this version does not know: nothing to compare with
            return
        raise ScanFormatError(
            f"scan_id {scan_id!r} was uploaded without a preset and read with the {ours.name} preset "
            f"({ours.range_resolution_m} m per range bin), but map {map_id!r} holds {theirs.name} scans "
            f"({theirs.range_resolution_m} m per range bin): upload it again with preset={theirs.name} (or "
            f"map_id={map_id}) in POST /scans, or send it inline")
