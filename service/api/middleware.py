"""ASGI middleware: request body size limits and request metrics."""

from __future__ import annotations

import json
import time
from collections.abc import Callable

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.core.metrics import Metrics

__all__ = ["BodyLimitMiddleware", "MetricsMiddleware"]


async def _reject(send: Send, status: int, detail: str, code: str) -> None:
    body = json.dumps({"detail": detail, "error": code}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})


#: Oversized bodies up to this many bytes above the limit are read and discarded before the 413 is sent.
_DRAIN_MAX_BYTES = 64 * 2**20


async def _drain(receive: Receive) -> None:
    while True:
        message = await receive()
        if message["type"] == "http.disconnect" or not message.get("more_body", False):
            return


class BodyLimitMiddleware:
    """Refuse bodies above a limit with 413 before the app parses them.

    ``limit_for(method, path)`` gives the byte limit of a request. With a Content-Length header the request
    is refused up front; chunked bodies are buffered up to the limit and refused as soon as they exceed it.
    """

    def __init__(self, app: ASGIApp, limit_for: Callable[[str, str], int]) -> None:
        self.app = app
        self.limit_for = limit_for

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.limit_for(scope["method"], scope["path"])
        headers = dict(scope.get("headers") or [])
        declared = headers.get(b"content-length")
        msg = f"request body larger than the limit of {limit / 2**20:.1f} MB"
        if declared is not None:
            try:
                size = int(declared)
            except ValueError:
                await _reject(send, 400, "invalid Content-Length header", "bad_request")
                return
            if size > limit:
                if size <= limit + _DRAIN_MAX_BYTES:
                    await _drain(receive)  # a client still sending would miss the answer on a reset socket
                await _reject(send, 413, msg, "payload_too_large")
                return
            await self.app(scope, receive, send)
            return
        if scope["method"] in ("GET", "HEAD", "DELETE", "OPTIONS"):
            await self.app(scope, receive, send)
            return
        chunks: list[bytes] = []
        total = 0
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            chunk = message.get("body", b"")
            total += len(chunk)
            if total > limit:
                while message.get("more_body", False) and total <= limit + _DRAIN_MAX_BYTES:
                    message = await receive()
                    total += len(message.get("body", b""))
                await _reject(send, 413, msg, "payload_too_large")
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        sent = False

        async def replay() -> Message:
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


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
            template = getattr(route, "path", None) or "unmatched"
            method = scope["method"]
            self.metrics.inc("reradar_http_requests_total", method=method, route=template,
                             status=str(status["code"]))
            self.metrics.observe("reradar_http_request_duration_seconds", time.perf_counter() - t0,
                                 method=method, route=template)
