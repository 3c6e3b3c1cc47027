"""``RedisSessionStore``: tracking sessions kept in Redis (shared by the workers of ``reradar serve --workers``
and by replicas), with the in-memory store's behaviour; Redis down forgets the session instead of failing."""

from __future__ import annotations

import math

import numpy as np
import redis

from reradar_core.localization import PosePrior
from reradar_core.matching.motion import MotionConfig
from service.core.sessions import SessionConfig
from service.core.shared_state import Keys, RedisSessionStore


class StubRedis:
    """The two calls the store makes, in a dict; ``down`` makes both raise as a lost connection does."""

    def __init__(self) -> None:
        self.data: dict[str, bytes] = {}
        self.ttl_ms: dict[str, int] = {}
        self.down = False

    def get(self, key: str) -> bytes | None:
        if self.down:
            raise redis.ConnectionError("down")
        return self.data.get(key)

    def set(self, key: str, value: str, px: int) -> None:
        if self.down:
            raise redis.ConnectionError("down")
        self.data[key] = value.encode()
        self.ttl_ms[key] = px


def _store(stub: StubRedis) -> RedisSessionStore:
    return RedisSessionStore(stub, Keys("t"), SessionConfig(ttl_s=30.0))  # type: ignore[arg-type]


def test_a_session_written_by_one_store_is_read_by_another() -> None:
    stub = StubRedis()
    a, b = _store(stub), _store(stub)  # two workers
    a.update("car-1", "demo", np.array([10.0, -2.0, 0.3]), None)
    key = "t:v1:session:demo:car-1"
    assert stub.ttl_ms[key] == 30_000
    prior = b.prior_for("car-1", "demo", np.array([1.0, 0.0, 0.0]))
    assert prior is not None
    np.testing.assert_allclose(prior.T_map_query[:2], [10.0 + math.cos(0.3), -2.0 + math.sin(0.3)])
    assert b.prior_for("car-1", "other-map", None) is None and b.prior_for("car-2", "demo", None) is None
    # not localized: the prior it was tracked from is kept (odometry keeps accumulating)
    moved = PosePrior(np.array([11.0, -1.7, 0.3]), 2.0, 0.1)
    b.update("car-1", "demo", None, moved)
    again = a.get("car-1", "demo")
    assert again is not None and again.sigma_xy_m == 2.0
    np.testing.assert_array_equal(again.T_map_query, moved.T_map_query)


def test_redis_down_or_a_bad_value_forgets_the_session() -> None:
    stub = StubRedis()
    s = _store(stub)
    s.update("car-1", "demo", np.zeros(3), None)
    stub.data["t:v1:session:demo:car-1"] = b"not json"
    assert s.get("car-1", "demo") is None
    stub.down = True
    assert s.get("car-1", "demo") is None
    s.update("car-1", "demo", np.zeros(3), None)  # no exception: the answer is still returned


def test_a_sessions_scan_times_give_the_next_prior_the_vehicles_motion() -> None:
    """Session 30: the scan's time is kept with the session's pose (in Redis too, so another worker reads it), and
    the next scan's odometry over the time between them is the prior's motion (the motion compensation's prior).
    A value written before (no time) still reads, without a motion."""
    from service.core.sessions import SessionStore

    stub = StubRedis()
    for a, b in ((_store(stub), _store(stub)), (SessionStore(), None)):
        b = b or a
        a.update("car-1", "demo", np.array([10.0, -2.0, 0.0]), None, timestamp_us=5_000_000)
        prior = b.prior_for("car-1", "demo", np.array([-1.0, 0.0, 0.0]), timestamp_us=5_250_000)  # reversing
        assert prior is not None and prior.timestamp_us == 5_250_000
        np.testing.assert_allclose(prior.twist, [-4.0, 0.0, 0.0], atol=1e-12)
        assert b.prior_for("car-1", "demo", np.zeros(3)).twist is None  # no time given: no motion
        stale = b.prior_for("car-1", "demo", np.zeros(3), timestamp_us=9_000_000)  # 4 s later: too long to say
        assert stale is not None and stale.twist is None
        # ... unless the service's motion settings allow it (RERADAR_LOCALIZATION__MOTION__MAX_KEYFRAME_GAP_S)
        allowed = b.prior_for("car-1", "demo", np.zeros(3), 9_000_000, MotionConfig(max_keyframe_gap_s=5.0))
        assert allowed is not None and allowed.twist is not None
        b.update("car-1", "demo", None, prior)  # not localized: the prior, its time included, is kept
        kept = a.get("car-1", "demo")
        assert kept is not None and kept.timestamp_us == 5_250_000
    stub.data["t:v1:session:demo:car-2"] = b'{"pose": [1, 2, 0], "sigma_xy_m": 0.5, "sigma_yaw_rad": 0.02}'
    old = _store(stub).get("car-2", "demo")
    assert old is not None and old.timestamp_us is None
    # a value no version writes (QA, session 30: these were a 500 on every scan of the session): forgotten
    for stamp in ("Infinity", "-Infinity", "1e400", "1" + "0" * 400, "1e19", "1.7", '"12"'):
        value = '{"pose": [1, 2, 0], "sigma_xy_m": 0.5, "sigma_yaw_rad": 0.02, "timestamp_us": ' + stamp + "}"
        stub.data["t:v1:session:demo:car-3"] = value.encode()
        assert _store(stub).get("car-3", "demo") is None
        assert _store(stub).prior_for("car-3", "demo", np.zeros(3), timestamp_us=1) is None
