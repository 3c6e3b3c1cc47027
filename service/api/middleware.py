"""ASGI middleware: the request guard (authentication, size, time and concurrency limits, all before the app
reads a body) and request metrics."""

from __future__ import annotations

import asyncio
import math
import tempfile
import time
from collections.abc import Callable, Iterable
from typing import IO, Any

from starlette.routing import Match, Mount, Route
from starlette.staticfiles import StaticFiles
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.security import Guard, RequestLimits, route_class
from service.core.errors import (
    PROBLEM_MEDIA_TYPE,
    BadRequestError,
    OverloadedError,
    PayloadTooLargeError,
    RequestTimeoutError,
    ServiceError,
    ServiceUnavailableError,
    TooManyRequestsError,
    problem_body,
)
from service.core.metrics import Metrics

__all__ = ["RequestGuardMiddleware", "MetricsMiddleware", "leaf_routes"]

#: Before a refusal, up to this many body bytes are read and discarded (never stored) so that a client still
#: sending sees the answer instead of a reset connection; larger bodies are cut off by closing the connection.
#: (The server cannot read a body after its answer: uvicorn reports a disconnect then.)
_DRAIN_MAX_BYTES = 64 * 2**20
#: ... and for at most this long.
_DRAIN_MAX_S = 5.0
#: Replayed body chunks (bytes).
_CHUNK = 1 << 20
#: Map uploads above this size are spooled to disk by the guard, not held in memory.
_SPOOL_MEMORY_BYTES = 4 * 2**20
_BODY_METHODS = ("POST", "PUT", "PATCH")


def leaf_routes(routes: Iterable[Any]) -> list[Route]:
    """The plain routes of an app, looking inside included routers (FastAPI wraps each ``include_router``);
    mounts (static files) are left out."""
    out: list[Route] = []
    for route in routes:
        if isinstance(route, Route):
            out.append(route)
        elif hasattr(route, "original_router"):
            out.extend(leaf_routes(route.original_router.routes))
        elif hasattr(route, "routes"):
            out.extend(leaf_routes(route.routes))
    return out


#: The methods a static file mount (``StaticFiles``) answers; any other is its 405.
STATIC_METHODS = ("GET", "HEAD")


def static_mount(scope: Scope) -> Mount | None:
    """The static file mount (``/ui/static``, ``/ui/vendor``) whose prefix ``scope``'s path falls under, if any."""
    router = getattr(scope.get("app"), "router", None)
    path = scope.get("path", "")  # the full path (inside a mount, ``matches`` would read it relative to it)
    for route in getattr(router, "routes", ()):
        if isinstance(route, Mount) and isinstance(route.app, StaticFiles) and path.startswith(route.path + "/"):
            return route
    return None


def _route_match(scope: Scope) -> tuple[str | None, bool]:
    """(template of the route that will answer ``scope``, whether it answers only with 405): the app's route
    matching path and method, else one matching the path only (405), else a static file mount (405 for a
    method other than GET / HEAD), else (None, False) (404). Used before the router has run (a guard refusal
    records no ``route`` in the scope)."""
    router = getattr(scope.get("app"), "router", None)
    partial: str | None = None
    for route in leaf_routes(getattr(router, "routes", ())):
        match, _ = route.matches(scope)
        if match == Match.FULL:
            return route.path, False
        if match == Match.PARTIAL and partial is None:
            partial = route.path
    if partial is None and (mount := static_mount(scope)) is not None:
        return mount.path, scope.get("method") not in STATIC_METHODS
    return partial, partial is not None


class _Refused(Exception):
    def __init__(self, error: ServiceError) -> None:
        super().__init__(error.message)
        self.error = error


async def _reply(send: Send, path: str, error: ServiceError) -> None:
    body = problem_body(error.status_code, error.code, error.message, instance=path)
    headers = [(b"content-type", PROBLEM_MEDIA_TYPE.encode()), (b"content-length", str(len(body)).encode()),
               (b"connection", b"close")]
    headers += [(k.lower().encode(), v.encode()) for k, v in error.headers.items()]
    await send({"type": "http.response.start", "status": error.status_code, "headers": headers})
    await send({"type": "http.response.body", "body": body})


async def _drain(receive: Receive, already_done: bool) -> None:
    """Discard what is left of the request body, within ``_DRAIN_MAX_BYTES`` and ``_DRAIN_MAX_S``."""
    if already_done:
        return
    total, deadline = 0, time.monotonic() + _DRAIN_MAX_S
    while total <= _DRAIN_MAX_BYTES:
        left = deadline - time.monotonic()
        if left <= 0:
            return
        try:
            message = await asyncio.wait_for(receive(), timeout=left)
        except TimeoutError:
            return
        if message["type"] == "http.disconnect":
            return
        total += len(message.get("body", b""))
        if not message.get("more_body", False):
            return


class _Body:
    """A request body received in full, held in memory or spooled to a temporary file."""

    def __init__(self, spool: IO[bytes] | None) -> None:
        self.chunks: list[bytes] = []
        self.spool = spool
        self.size = 0

    def add(self, chunk: bytes) -> None:
        self.size += len(chunk)
        if self.spool is not None:
            self.spool.write(chunk)
        else:
            self.chunks.append(chunk)

    def replay(self, receive: Receive) -> Receive:
        if self.spool is not None:
            self.spool.seek(0)
        index = 0
        done = False

        async def replayed() -> Message:
            nonlocal done, index
            if done:
                return await receive()  # e.g. http.disconnect while the app streams its answer
            if self.spool is not None:
                data = self.spool.read(_CHUNK)
                more = self.spool.tell() < self.size
            else:
                data = self.chunks[index] if index < len(self.chunks) else b""
                if index < len(self.chunks):
                    self.chunks[index] = b""  # the app holds (or has parsed) it now: do not keep a copy
                index += 1
                more = index < len(self.chunks)
            done = not more
            return {"type": "http.request", "body": data, "more_body": more}

        return replayed

    def close(self) -> None:
        if self.spool is not None:
            self.spool.close()


#: The body's average rate is checked from this many seconds after its start (``min_rate``)
RATE_GRACE_S = 5.0


async def _receive_body(receive: Receive, limit: int, idle_s: float, total_s: float,
                        spool: IO[bytes] | None, min_rate: float = 0.0) -> _Body | None:
    """The whole body, or None when the client disconnected.

    ``min_rate`` (bytes/s, 0: none): from ``RATE_GRACE_S`` after the start, the body must have arrived at this
    average rate at least. A client trickling a body holds one of the few request slots
    (``RequestLimits.max_concurrent``): four sending a byte every 5 s locked every scan request out for the
    whole ``total_s`` (QA, session 22); the rate cuts them off after the grace.

    Raises:
        _Refused: 413 above ``limit`` bytes, 408 when no data arrives for ``idle_s``, the body arrives slower
        than ``min_rate`` or is not complete within ``total_s`` seconds.
    """
    body = _Body(spool)
    start = time.monotonic()
    deadline = start + total_s
    while True:
        now = time.monotonic()
        left = deadline - now
        # the moment by which the bytes received so far fall below the minimum average rate
        behind = start + RATE_GRACE_S + body.size / min_rate - now if min_rate > 0 else math.inf
        wait = min(idle_s, left, behind)
        try:
            if wait <= 0:
                raise TimeoutError
            message = await asyncio.wait_for(receive(), timeout=wait)
        except TimeoutError:
            body.close()
            if wait == behind:
                elapsed = time.monotonic() - start
                why = (f"the request body arrived at {body.size / max(elapsed, 1e-9) / 1024:.1f} KiB/s, below the "
                       f"minimum of {min_rate / 1024:.0f} KiB/s")
            elif left <= idle_s:
                why = f"the request body was not complete within {total_s:.0f} s"
            else:
                why = f"the client sent no request body data for {idle_s:.0f} s"
            raise _Refused(RequestTimeoutError(why + "; send the whole body at once")) from None
        if message["type"] == "http.disconnect":
            body.close()
            return None
        body.add(message.get("body", b""))
        if body.size > limit:
            body.close()
            raise _Refused(PayloadTooLargeError(f"request body larger than the limit of {limit / 2**20:.1f} MB"))
        if not message.get("more_body", False):
            return body


class RequestGuardMiddleware:
    """Refuse what would cost the server before it costs anything.

    For every HTTP request, in this order: authenticate scan and map requests (``X-API-Key``, see
    ``service.api.security``) from the headers alone; refuse a declared ``Content-Length`` above the limit
    (413); refuse a scan or map request when its API key already has ``max_concurrent_per_key`` in progress (429 +
    ``Retry-After``), or when ``max_concurrent`` are in progress (503 + ``Retry-After``);
    receive the body within the idle and total timeouts (408) and the size limit (413), then hand it to the app.
    ``get_guard()`` is None while the service starts: scan and map requests then get 503 too. Two
    ``X-API-Key`` headers are refused (400: ambiguous credentials); a request the guard would refuse whose
    method the path does not serve is answered 405 by the app instead, with or without a key.
    """

    def __init__(self, app: ASGIApp, get_guard: Callable[[], Guard | None],
                 default_limits: Callable[[], RequestLimits]) -> None:
        self.app = app
        self.get_guard = get_guard
        self.default_limits = default_limits
        self.in_flight = 0
        self.in_flight_by_caller: dict[str, int] = {}  # per API key (``AccessPolicy.caller_id``)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        method, path = scope["method"], scope["path"]
        kind = route_class(method, path)
        guard = self.get_guard()
        headers = dict(scope.get("headers") or [])
        declared = headers.get(b"content-length")
        no_body = declared in (None, b"0") and b"transfer-encoding" not in headers
        # a client that waits for "100 Continue" has sent nothing yet: refuse it without asking for the body
        skip_drain = no_body or headers.get(b"expect", b"").lower() == b"100-continue"
        if kind != "public":
            try:
                if guard is None:
                    raise ServiceUnavailableError("the service is still loading the model and maps; retry shortly")
                keys = [v for k, v in scope.get("headers") or [] if k.lower() == b"x-api-key"]
                if len(keys) > 1:
                    raise BadRequestError(f"ambiguous credentials: {len(keys)} X-API-Key headers; send exactly one")
                key = keys[0].decode("latin-1") if keys else None
                client = scope.get("client")
                principal = guard.policy.authorize(kind, key or None, client[0] if client else None)
            except ServiceError as exc:
                if _route_match(scope)[1]:
                    # a method the path does not serve: 405 (with Allow) from the app, whoever asks (the answer
                    # tells nothing the public OpenAPI document does not); no body is read
                    await self.app(scope, receive, send)
                    return
                await _drain(receive, skip_drain)
                await _reply(send, path, exc)
                return
            scope.setdefault("state", {})["principal"] = principal
            if principal is not None:
                scope["state"]["caller"] = guard.policy.caller_id(principal, key)
        limits = guard.limits if guard is not None else self.default_limits()
        is_map_upload = kind == "operator" and method == "POST"
        limit = limits.max_map_body_bytes if is_map_upload else limits.max_body_bytes
        if declared is not None:
            try:
                size = int(declared)
                if size < 0:
                    raise ValueError
            except ValueError:
                await _reply(send, path, ServiceError("invalid Content-Length header"))
                return
            if size > limit:
                await _drain(receive, skip_drain)
                await _reply(send, path, PayloadTooLargeError(
                    f"request body larger than the limit of {limit / 2**20:.1f} MB"))
                return
        heavy = kind != "public" and method in _BODY_METHODS
        caller = scope.get("state", {}).get("caller")
        if caller == "loopback":  # keyless local clients: one trusted setup, not limited per key
            caller = None
        if heavy:
            per_key = limits.max_concurrent_per_key
            if caller is not None and per_key is not None and self.in_flight_by_caller.get(caller, 0) >= per_key:
                await _drain(receive, skip_drain)
                await _reply(send, path, TooManyRequestsError(
                    f"this API key already has {per_key} scan / map requests in progress, the most one key may have "
                    f"at once; retry in {limits.retry_after_s} s", retry_after_s=limits.retry_after_s))
                return
            if self.in_flight >= limits.max_concurrent:
                await _drain(receive, skip_drain)
                await _reply(send, path, OverloadedError(
                    f"the server is busy with {limits.max_concurrent} scan / map requests; retry in "
                    f"{limits.retry_after_s} s", retry_after_s=limits.retry_after_s))
                return
            self.in_flight += 1
            if caller is not None:
                self.in_flight_by_caller[caller] = self.in_flight_by_caller.get(caller, 0) + 1
        try:
            if method not in _BODY_METHODS or no_body:
                await self.app(scope, receive, send)
                return
            spool: IO[bytes] | None = None
            if is_map_upload:
                spool = tempfile.SpooledTemporaryFile(  # noqa: SIM115 - closed by _Body
                    max_size=_SPOOL_MEMORY_BYTES, dir=str(limits.spool_dir) if limits.spool_dir else None)
            total_s = limits.map_upload_timeout_s if is_map_upload else limits.body_timeout_s
            try:
                body = await _receive_body(receive, limit, limits.body_idle_timeout_s, total_s, spool,
                                           limits.body_min_rate_bytes_s)
            except _Refused as exc:
                if exc.error.status_code == 413:
                    await _drain(receive, False)
                await _reply(send, path, exc.error)
                return
            if body is None:
                return
            try:
                await self.app(scope, body.replay(receive), send)
            finally:
                body.close()
        finally:
            if heavy:
                self.in_flight -= 1
                if caller is not None:
                    left = self.in_flight_by_caller[caller] - 1
                    if left:
                        self.in_flight_by_caller[caller] = left
                    else:
                        del self.in_flight_by_caller[caller]


#: Request methods counted under their own name; any other (a client may send any token) counts as ``other``,
#: so made-up methods cannot grow the metrics without bound (QA, session 21: 25,000 requests, a 45 MB /metrics).
KNOWN_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})


class MetricsMiddleware:
    """Count requests and observe latency by method, route template and status."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        status = {"code": 500}
        t0 = time.perf_counter()

        async def send_wrapper(message: Message) -> None:
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            route = scope.get("route")
            # requests the guard refused never reached the router: count them under the route they asked for
            template = getattr(route, "path", None) or _route_match(scope)[0] or "unmatched"
            method = scope["method"] if scope["method"] in KNOWN_METHODS else "other"
            self.metrics.inc("reradar_http_requests_total", method=method, route=template,
                             status=str(status["code"]))
            self.metrics.observe("reradar_http_request_duration_seconds", time.perf_counter() - t0,
                                 method=method, route=template)
