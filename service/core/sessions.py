"""Tracking sessions: the last pose of each vehicle session per map, kept in memory (bounded, expiring);
``service.core.shared_state.RedisSessionStore`` keeps them in Redis instead, shared by every worker and replica.

A session's state is a ``PosePrior``: after a localized scan, the answer with the localizer's accuracy
(``fix_sigma_*``); after a scan that was not localized, the prior it was tracked from (the previous state
moved by the reported odometry: its uncertainty grows), or - when the scan came without odometry - the last
pose marked unknown (``lost_sigma_m``). ``prior_for`` turns the state plus the request's odometry into the
prior the next scan is tracked from.

Without odometry there is no prior: the last pose says where the vehicle was, not where it is. At 8 m/s and
4 Hz it moved 2 m; a skipped scan or a faster vehicle, 6-15 m. Registration started at the last pose settled
next to it and passed the 18 m gate of the 6 m sigma it used to get (``reradar localize --follow`` on the QA
drive at 8 m/s: 0.1, 0.4, 1.0 ... 7.4 m off, all ``localized``), so such a scan is localized globally, exactly
as without a session, and the session keeps its answer for the next scan that brings odometry.
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
from reradar_core.matching.motion import MotionConfig

__all__ = ["SessionStore", "SessionConfig"]


@dataclass(frozen=True)
class SessionConfig:
    """Session bookkeeping (metres, degrees, seconds).

    Attributes:
        max_sessions: sessions kept (least recently used dropped first).
        ttl_s: a session unused this long is forgotten (the next scan is localized globally).
        fix_sigma_m / fix_sigma_yaw_deg: uncertainty of a localized answer (measured errors are ~0.2-1 m,
            ~0.5 deg; these leave margin).
        odometry_sigma_growth: uncertainty added per metre (and per radian) of reported odometry.
        lost_sigma_m: uncertainty of a session whose vehicle moved by an unknown amount (a scan without
            odometry that was not localized): far above any prior the tracker covers
            (``TrackingConfig.covers``), so its next scans are localized globally until one is localized.
    """

    max_sessions: int = 10_000
    ttl_s: float = 60.0
    fix_sigma_m: float = 0.5
    fix_sigma_yaw_deg: float = 1.0
    odometry_sigma_growth: float = 0.1
    lost_sigma_m: float = 1.0e4


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

    def prior_for(self, session_id: str, map_id: str, odometry: np.ndarray | None,
                  timestamp_us: int | None = None, motion: MotionConfig | None = None) -> PosePrior | None:
        """The prior to track the session's next scan from: the state moved by ``odometry`` ((3,) x m, y m,
        yaw rad in the previous scan's frame). None when the session has no state or without odometry (the
        scan is then localized globally; module docstring). The prior may still be too loose to track from
        (after a long stretch without a fix, or a lost session): the caller asks ``TrackingConfig.covers``.
        ``timestamp_us``: the new scan's time; with the last scan's, the odometry gives the vehicle's motion
        (``PosePrior.twist``: the motion compensation's prior) under ``motion`` (the service's localization
        settings' ``motion``; default ``MotionConfig()``)."""
        if odometry is None:
            return None
        state = self.get(session_id, map_id)
        if state is None:
            return None
        return state.moved(odometry, self.config.odometry_sigma_growth, timestamp_us=timestamp_us,
                           motion_config=motion)

    def update(self, session_id: str, map_id: str, T_map_query: np.ndarray | None,
               prior: PosePrior | None, timestamp_us: int | None = None) -> None:
        """Record the outcome of a scan (taken at ``timestamp_us``, when known): its pose when localized; else the
        prior it was tracked from (so odometry keeps accumulating); else - no prior: the scan came without odometry
        (``prior_for``), so the vehicle moved an unknown distance - the last pose with ``lost_sigma_m`` (no later
        scan is tracked from it)."""
        c = self.config
        state: PosePrior | None
        if T_map_query is not None:
            state = PosePrior(T_map_query, c.fix_sigma_m, math.radians(c.fix_sigma_yaw_deg), timestamp_us)
        elif prior is None:
            last = self.get(session_id, map_id)
            state = None if last is None else PosePrior(last.T_map_query, c.lost_sigma_m, math.pi)
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
