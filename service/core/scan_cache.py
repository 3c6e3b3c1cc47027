"""Bounded, expiring cache of uploaded scans' features (``POST /scans`` -> ``scan_id``), in this process.

A ``cachetools.TTLCache`` (least recently used out first, every entry expires ``ttl_s`` after it was put).
A scan is its uploader's (``owner``: the caller, ``AccessPolicy.caller_id``): another API key's ``scan_id`` is
unknown to a caller, and one caller holds at most a quarter of the entries (``per_owner``), so one key uploading
fast evicts its own oldest scans, not another vehicle's. With several replicas the shared Redis store
(``service.core.shared_state.RedisScanStore``) replaces it.
"""

from __future__ import annotations

import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
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
    #: who uploaded it (``AccessPolicy.caller_id``); only that caller can use the ``scan_id``
    owner: str = "loopback"
    #: the scan's far-view dense image (``matching.dense.dense_image``, float16, ~130 KB at 257 px; computed at upload
    #: while a loaded map's far-view companion holds dense images), or None: no dense registration by this ``scan_id``
    dense_image: np.ndarray | None = None


class ScanCache:
    """LRU cache with a time-to-live: at most ``max_entries`` scans, each kept ``ttl_s`` seconds, at most
    ``per_owner`` (default a quarter of ``max_entries``) of one caller's."""

    def __init__(self, max_entries: int, ttl_s: float, clock: Callable[[], float] = time.monotonic,
                 per_owner: int | None = None) -> None:
        self.max_entries = max_entries
        self.ttl_s = ttl_s
        self.per_owner = max(1, per_owner if per_owner is not None else max_entries // 4)
        self._clock = clock
        self._items: TTLCache[str, CachedScan] = TTLCache(maxsize=max_entries, ttl=ttl_s, timer=clock)
        self._owned: dict[str, OrderedDict[str, None]] = {}  # owner -> its scan ids, least recently used first
        self._lock = threading.Lock()  # cachetools caches are not thread-safe

    def put(self, features: ScanFeatures, preset: str | None, preset_open: bool = False,
            far_features: ScanFeatures | None = None, owner: str = "loopback",
            dense_image: np.ndarray | None = None) -> CachedScan:
        """Store ``features`` (and the far view's and its dense image, when given) under a new random id for
        ``owner``: beyond its ``per_owner`` scans its own least recently used goes first, beyond ``max_entries`` the
        least recently used of all."""
        entry = CachedScan(new_scan_id(), features, preset, preset_open, far_features, owner,
                           None if dense_image is None else np.asarray(dense_image, np.float16))
        with self._lock:
            self._items.expire()
            ids = self._owned.setdefault(owner, OrderedDict())
            for sid in [sid for sid in ids if sid not in self._items]:  # expired or evicted meanwhile
                del ids[sid]
            while len(ids) >= self.per_owner:
                self._items.pop(ids.popitem(last=False)[0], None)
            self._items[entry.scan_id] = entry
            ids[entry.scan_id] = None
            for other in [o for o, held in self._owned.items() if not held]:
                del self._owned[other]
        return entry

    def get(self, scan_id: str, owner: str = "loopback") -> CachedScan | None:
        """The entry for ``scan_id`` or None when unknown, expired, or another caller's than ``owner``."""
        with self._lock:
            entry = self._items.get(scan_id)
            if entry is None or entry.owner != owner:
                return None
            ids = self._owned.get(entry.owner)
            if ids is not None and scan_id in ids:
                ids.move_to_end(scan_id)  # least recently used goes first within the owner's share too
        return entry

    def __len__(self) -> int:
        with self._lock:
            self._items.expire()
            return len(self._items)
