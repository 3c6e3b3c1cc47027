"""Bounded, expiring cache of uploaded scans' features (``POST /scans`` -> ``scan_id``)."""

from __future__ import annotations

import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

from reradar_core.features import ScanFeatures

__all__ = ["CachedScan", "ScanCache"]


@dataclass(frozen=True)
class CachedScan:
    """Features of one uploaded scan with its id, radar preset and expiry (``time.monotonic`` seconds)."""

    scan_id: str
    features: ScanFeatures
    preset: str | None
    expires_at: float


class ScanCache:
    """LRU cache with a time-to-live: at most ``max_entries`` scans, each kept ``ttl_s`` seconds."""

    def __init__(self, max_entries: int, ttl_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.max_entries = max_entries
        self.ttl_s = ttl_s
        self._clock = clock
        self._items: OrderedDict[str, CachedScan] = OrderedDict()
        self._lock = threading.Lock()

    def _purge(self, now: float) -> None:
        expired = [k for k, v in self._items.items() if v.expires_at <= now]
        for k in expired:
            del self._items[k]

    def put(self, features: ScanFeatures, preset: str | None) -> CachedScan:
        """Store ``features`` under a new random id (evicting the least recently used beyond the bound)."""
        now = self._clock()
        entry = CachedScan(secrets.token_hex(16), features, preset, now + self.ttl_s)
        with self._lock:
            self._purge(now)
            self._items[entry.scan_id] = entry
            while len(self._items) > self.max_entries:
                self._items.popitem(last=False)
        return entry

    def get(self, scan_id: str) -> CachedScan | None:
        """The entry for ``scan_id`` or None when unknown or expired."""
        now = self._clock()
        with self._lock:
            entry = self._items.get(scan_id)
            if entry is None:
                return None
            if entry.expires_at <= now:
                del self._items[scan_id]
                return None
            self._items.move_to_end(scan_id)
            return entry

    def __len__(self) -> int:
        with self._lock:
            self._purge(self._clock())
            return len(self._items)
