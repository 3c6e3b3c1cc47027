"""Tracking sessions: the last pose of each vehicle session per map, kept in memory (bounded, expiring);
``service.core.shared_state.RedisSessionStore`` keeps them in Redis instead, shared by every worker and replica.

A session's state is a ``PosePrior``: after a localized scan, the answer with the localizer's accuracy
(``fix_sigma_*``); after a scan that was not localized, the previous prior moved by the reported odometry
(its uncertainty grows), or unchanged. ``prior_for`` turns the state plus the request's odometry into the
prior the next scan is tracked from; without odometry the vehicle may have moved anywhere nearby, so the
prior gets ``no_odometry_sigma_*``.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from reradar_core.localization import PosePrior

__all__ = ["SessionStore", "SessionConfig"]


@dataclass(frozen=True)
class SessionConfig:
    """Session bookkeeping (metres, degrees, seconds).

    Attributes:
        max_sessions: sessions kept (least recently used dropped first).
        ttl_s: a session unused this long is forgotten (the next scan is localized globally).
        fix_sigma_m / fix_sigma_yaw_deg: uncertainty of a localized answer (measured errors are ~0.2-1 m,
            ~0.5 deg; these leave margin).
        no_odometry_sigma_m / no_odometry_sigma_yaw_deg: prior uncertainty when no odometry is sent (a vehicle
            at 20 m/s moves ~5 m between 4 Hz scans).
        odometry_sigma_growth: uncertainty added per metre (and per radian) of reported odometry.
    """

    max_sessions: int = 10_000
    ttl_s: float = 60.0
    fix_sigma_m: float = 0.5
    fix_sigma_yaw_deg: float = 1.0
    no_odometry_sigma_m: float = 6.0
    no_odometry_sigma_yaw_deg: float = 10.0
    odometry_sigma_growth: float = 0.1


class SessionStore:
    """Thread-safe, bounded, expiring map (session id, map id) -> ``PosePrior``."""

    def __init__(self, config: SessionConfig | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config or SessionConfig()
        self._clock = clock
        self._items: OrderedDict[tuple[str, str], tuple[float, PosePrior]] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._items)

    def get(self, session_id: str, map_id: str) -> PosePrior | None:
        """The session's state on this map, or None (unknown or expired)."""
        key = (session_id, map_id)
        with self._lock:
            item = self._items.get(key)
            if item is None:
                return None
            if self._clock() - item[0] > self.config.ttl_s:
                del self._items[key]
                return None
            self._items.move_to_end(key)
            return item[1]

    def prior_for(self, session_id: str, map_id: str, odometry: np.ndarray | None) -> PosePrior | None:
        """The prior to track the session's next scan from, or None when the session has no state."""
        state = self.get(session_id, map_id)
        if state is None:
            return None
        c = self.config
        if odometry is None:
            return PosePrior(state.T_map_query, max(state.sigma_xy_m, c.no_odometry_sigma_m),
                             max(state.sigma_yaw_rad, math.radians(c.no_odometry_sigma_yaw_deg)))
        return state.moved(odometry, c.odometry_sigma_growth)

    def update(self, session_id: str, map_id: str, T_map_query: np.ndarray | None,
               prior: PosePrior | None) -> None:
        """Record the outcome of a scan: its pose when localized, else the prior it was tracked from (so
        odometry keeps accumulating), else nothing."""
        c = self.config
        if T_map_query is not None:
            state: PosePrior | None = PosePrior(T_map_query, c.fix_sigma_m, math.radians(c.fix_sigma_yaw_deg))
        else:
            state = prior
        if state is None:
            return
        self._store(session_id, map_id, state)

    def _store(self, session_id: str, map_id: str, state: PosePrior) -> None:
        with self._lock:
            self._items[(session_id, map_id)] = (self._clock(), state)
            self._items.move_to_end((session_id, map_id))
            while len(self._items) > self.config.max_sessions:
                self._items.popitem(last=False)
