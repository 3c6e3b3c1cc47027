"""Who may call what: operator and vehicle keys, and the request limits the guard enforces before a body is read.

Route classes:

=========  ==========================================================  =====================================
class      routes                                                      key (``X-API-Key`` header)
=========  ==========================================================  =====================================
operator   ``POST /maps``, ``DELETE /maps/{id}`` (any write under       the operator key
           ``/maps`` except retrieve)
vehicle    ``POST /scans``, ``POST /localize``, ``POST /maps/{id}/      a vehicle key or the operator key;
           retrieve``, any method under ``/ui/api/`` (the operator     none needed from loopback clients when
           page's data: vehicle positions), and any other write        no vehicle key is configured
           method on any path
public     ``GET`` / ``HEAD`` / ``OPTIONS``: health, metrics, maps,     none
           docs, the operator page and its static files
=========  ==========================================================  =====================================
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from starlette.requests import Request

from service.core.config import Settings, is_loopback, resolve_operator_key
from service.core.errors import ServiceError, UnauthorizedError

__all__ = ["RouteClass", "Principal", "AccessPolicy", "RequestLimits", "Guard", "route_class", "ForbiddenError",
           "build_guard", "caller_of"]

RouteClass = Literal["operator", "vehicle", "public"]
Principal = Literal["operator", "vehicle", "loopback"]


class ForbiddenError(ServiceError):
    status_code = 403
    code = "forbidden"


def route_class(method: str, path: str) -> RouteClass:
    """The access class of a request (see the module docstring). Safe by default: a write method on any
    path not named here (a route added later, an unknown path) is a vehicle route, never public."""
    p = path.rstrip("/") or "/"
    parts = p.split("/")
    if len(parts) >= 3 and parts[1] == "ui" and parts[2] == "api":
        return "vehicle"  # where vehicles were: the same rule as the routes that answer where a vehicle is
    if method in ("GET", "HEAD", "OPTIONS"):
        return "public"
    if len(parts) >= 2 and parts[1] == "maps" and not (len(parts) == 4 and parts[3] == "retrieve"):
        return "operator"  # POST /maps, DELETE /maps/{id}, and any other change to maps
    return "vehicle"


def _matches(key: str, candidates: tuple[str, ...]) -> bool:
    hit = False
    for c in candidates:  # compare with every key: the time taken does not tell which key was close
        hit |= secrets.compare_digest(key.encode(), c.encode())
    return hit


@dataclass(frozen=True)
class AccessPolicy:
    """The operator key, the vehicle keys and whether loopback clients may use vehicle routes without a key."""

    operator_key: str
    vehicle_keys: tuple[str, ...] = ()
    anonymous_loopback: bool = True

    def caller_id(self, principal: Principal, key: str | None) -> str:
        """Who is calling, for what a caller keeps between requests (tracking sessions): each API key its own, as
        an HMAC of the key under the operator key (the same on every replica; without the operator key it tells
        nothing about the key, so it may appear in Redis keys and logs); every keyless loopback client one. Two
        vehicles that share a key share it."""
        if principal == "loopback" or not key:
            return "loopback"
        mac = hmac.new(self.operator_key.encode("utf-8", "surrogateescape"), key.encode("utf-8", "surrogateescape"),
                       hashlib.sha256)
        return "key-" + mac.hexdigest()[:16]

    def authorize(self, kind: RouteClass, key: str | None, client_host: str | None) -> Principal | None:
        """The caller's principal for a route of class ``kind``.

        Raises:
            UnauthorizedError: missing or unknown key. ForbiddenError: a vehicle key on an operator route.
        """
        if kind == "public":
            return None
        if key:
            if _matches(key, (self.operator_key,)):
                return "operator"
            if _matches(key, self.vehicle_keys):
                if kind == "operator":
                    raise ForbiddenError("a vehicle key cannot register or delete maps; use the operator key")
                return "vehicle"
            raise UnauthorizedError("wrong API key in the X-API-Key header")
        if kind == "vehicle" and self.anonymous_loopback and not self.vehicle_keys and is_loopback(client_host):
            return "loopback"
        if kind == "operator":
            raise UnauthorizedError("this endpoint needs the operator key in the X-API-Key header "
                                    "(RERADAR_API_KEY, or the generated key in the maps folder's .operator-key)")
        raise UnauthorizedError("this endpoint needs a vehicle key in the X-API-Key header (RERADAR_VEHICLE_KEYS); "
                                "without configured vehicle keys it answers only clients on the loopback interface")


def caller_of(request: Request) -> str:
    """Who is calling (``AccessPolicy.caller_id``, set by the request guard): what a caller keeps between requests
    (tracking sessions, uploaded scans) is its own. ``loopback`` for keyless local clients."""
    return str(request.scope.get("state", {}).get("caller", "loopback"))


@dataclass(frozen=True)
class RequestLimits:
    """Body size and time limits, and the number of scan / map requests served at once."""

    max_body_bytes: int
    max_map_body_bytes: int
    body_idle_timeout_s: float
    body_timeout_s: float
    map_upload_timeout_s: float
    max_concurrent: int
    retry_after_s: int
    spool_dir: Path | None = None
    body_min_rate_bytes_s: float = 0.0
    max_concurrent_per_key: int | None = None  # None: no per-key limit

    @classmethod
    def from_settings(cls, s: Settings) -> RequestLimits:
        return cls(s.max_upload_bytes, s.max_map_upload_bytes, s.body_idle_timeout_s, s.body_timeout_s,
                   s.map_upload_timeout_s, s.max_concurrent_requests, s.retry_after_s,
                   body_min_rate_bytes_s=s.body_min_rate_kib_s * 1024, max_concurrent_per_key=s.max_concurrent_per_key)


@dataclass(frozen=True)
class Guard:
    """What the request guard needs once the service has started."""

    policy: AccessPolicy
    limits: RequestLimits


def build_guard(settings: Settings, spool_dir: Path | None = None) -> Guard:
    """The guard of a starting service (resolves, and on first start generates, the operator key)."""
    policy = AccessPolicy(resolve_operator_key(settings), tuple(settings.vehicle_key_list),
                          anonymous_loopback=settings.environment != "production")
    limits = RequestLimits.from_settings(settings)
    if spool_dir is not None:
        limits = RequestLimits(**{**limits.__dict__, "spool_dir": spool_dir})
    return Guard(policy, limits)
