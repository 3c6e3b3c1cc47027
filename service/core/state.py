"""Everything the routes share, created in the app's lifespan handler (never at import)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from reradar_core.errors import ScanFormatError
from reradar_core.features import ScanFeatures
from reradar_core.io.scan import NpyLayout, load_scan_bytes
from reradar_core.localization import LocalizationConfig
from reradar_core.localization.extractor import FeatureExtractor
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
                        scan_layout: NpyLayout = "polar", map_id: str | None = None) -> tuple[ScanFeatures, str | None]:
        """Decode an uploaded scan (PNG / .npy, an .npy as ``scan_layout``) and compute its features; adds
        ``decode_ms``/``extract_ms``. Without ``preset``, the geometry of the ready map ``map_id`` is used where
        the scan fits it (``load_scan_bytes``'s ``map_preset``).

        Raises:
            ScanFormatError: empty, corrupt or wrongly shaped scans, non-finite features.
        """
        if not data:
            raise ScanFormatError("the uploaded scan file is empty")
        t0 = time.perf_counter()
        # the sides were checked on the upload's header (``scan_input.check_scan_upload``, every caller's path)
        scan = load_scan_bytes(data, filename or "scan.png", preset, scan_layout, self.map_preset(map_id))
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
        return features, scan.preset
