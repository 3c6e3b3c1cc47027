"""``RedisSessionStore``: tracking sessions kept in Redis (shared by the workers of ``reradar serve --workers``
and by replicas), with the in-memory store's behaviour; Redis down forgets the session instead of failing."""

from __future__ import annotations

import math

import numpy as np
import redis

from reradar_core.localization import PosePrior
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
