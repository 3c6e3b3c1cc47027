"""Bounded, expiring cache of uploaded scans' features (``POST /scans`` -> ``scan_id``), in this process.

A ``cachetools.TTLCache`` (least recently used out first, every entry expires ``ttl_s`` after it was put).
With several replicas the shared Redis store (``service.core.shared_state.RedisScanStore``) replaces it.
"""

from __future__ import annotations

import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from cachetools import TTLCache

from reradar_core.features import ScanFeatures

__all__ = ["CachedScan", "ScanCache", "new_scan_id"]


def new_scan_id() -> str:
    """A fresh random scan id: 32 lower-case hex characters (128 bits)."""
    return secrets.token_hex(16)


@dataclass(frozen=True)
class CachedScan:
    """Features of one uploaded scan with its id and radar preset (the cache keeps it for its TTL)."""

    scan_id: str
    features: ScanFeatures
    preset: str | None
    #: no preset was given and the scan does not fix one: ``preset`` is a guess or the upload's map's
    #: (``describe_upload``); such a scan is refused on a map of another range geometry (``check_cached_preset``)
    preset_open: bool = False
    #: the scan's far-view features (computed at upload while a loaded map has a far-view companion, ``POST
    #: /scans``), or None: a request by this ``scan_id`` is then answered in the map's own view only
    far_features: ScanFeatures | None = None


class ScanCache:
    """LRU cache with a time-to-live: at most ``max_entries`` scans, each kept ``ttl_s`` seconds."""

    def __init__(self, max_entries: int, ttl_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.max_entries = max_entries
        self.ttl_s = ttl_s
        self._clock = clock
        self._items: TTLCache[str, CachedScan] = TTLCache(maxsize=max_entries, ttl=ttl_s, timer=clock)
        self._lock = threading.Lock()  # cachetools caches are not thread-safe

    def put(self, features: ScanFeatures, preset: str | None, preset_open: bool = False,
            far_features: ScanFeatures | None = None) -> CachedScan:
        """Store ``features`` (and the far view's, when given) under a new random id (evicting the least recently
        used beyond the bound)."""
        entry = CachedScan(new_scan_id(), features, preset, preset_open, far_features)
        with self._lock:
            self._items[entry.scan_id] = entry
        return entry

    def get(self, scan_id: str) -> CachedScan | None:
        """The entry for ``scan_id`` or None when unknown or expired."""
        with self._lock:
            return self._items.get(scan_id)

    def __len__(self) -> int:
        with self._lock:
            self._items.expire()
            return len(self._items)
