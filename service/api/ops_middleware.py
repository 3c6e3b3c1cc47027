"""ASGI middleware feeding the operator page and the other replicas, without touching the routes.

- ``POST /localize`` answered 200: the outcome (pose, confidence, latency) goes to the recent localizations
  of its map (``OpsRuntime.recent``: Redis, or memory in one process), with the map's version, so that an answer
  finishing after a DELETE is not shown on another map registered under the id.
- ``POST /maps`` answered 201 and ``DELETE /maps/{id}`` answered 200: a map event is published so every
  replica loads or drops the map (``MapSync``); queued builds publish their own events.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import time
from typing import Any

from starlette.concurrency import run_in_threadpool
from starlette.types import ASGIApp, Message, Receive, Scope, Send

__all__ = ["OpsMiddleware", "localization_record"]

logger = logging.getLogger(__name__)

#: Largest localize response buffered for the record (responses are a few KB).
_MAX_BODY = 1 << 20


def localization_record(body: dict[str, Any], latency_ms: float, origin: str) -> dict[str, Any]:
    """What the operator page shows of one ``POST /localize`` response (metres, degrees, milliseconds).

    ``confidence`` is the response's own ``confidence`` when it has one, else its inlier ratio (the
    fraction of query landmarks the pose aligns).
    """
    pose = body.get("pose") or None
    keyframe = body.get("keyframe") or {}
    confidence = body.get("confidence", body.get("inlier_ratio"))
    return {
        "utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z"),
        "map_id": body.get("map_id"),
        "status": body.get("status"),
        "reason": body.get("reason"),
        "x_m": pose.get("x_m") if pose else None,
        "y_m": pose.get("y_m") if pose else None,
        "yaw_deg": pose.get("yaw_deg") if pose else None,
        "keyframe_id": keyframe.get("keyframe_id"),
        "num_inliers": body.get("num_inliers"),
        "confidence": confidence,
        "latency_ms": round(latency_ms, 1),
        "server_ms": (body.get("timings_ms") or {}).get("total_ms"),
        "replica": origin,
    }


class OpsMiddleware:
    """Record localizations and publish map events (see the module doc)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        method, path = scope["method"], scope["path"].rstrip("/") or "/"
        is_localize = method == "POST" and path == "/localize"
        is_map_change = (method == "POST" and path == "/maps") or (method == "DELETE" and path.startswith("/maps/")
                                                                   and path.count("/") == 2)
        if not (is_localize or is_map_change):
            await self.app(scope, receive, send)
            return
        t0 = time.perf_counter()
        status = {"code": 0}
        chunks: list[bytes] = []

        async def send_wrapper(message: Message) -> None:
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
            elif message["type"] == "http.response.body" and status["code"] in (200, 201):
                if sum(map(len, chunks)) < _MAX_BODY:
                    chunks.append(message.get("body", b""))
            await send(message)

        await self.app(scope, receive, send_wrapper)
        app = scope.get("app")
        ops = getattr(app.state, "ops", None) if app is not None else None
        if ops is None or status["code"] not in (200, 201):
            return
        try:
            body = json.loads(b"".join(chunks))
        except ValueError:
            return
        if not isinstance(body, dict):
            return
        if is_localize and status["code"] == 200 and body.get("map_id"):
            record = localization_record(body, (time.perf_counter() - t0) * 1e3, ops.origin)
            record["map_version"] = scope.get("state", {}).get("map_version")  # the localize route's map version
            await run_in_threadpool(ops.recent.add, body["map_id"], record)
        elif is_map_change and body.get("id"):
            if method == "DELETE":
                await run_in_threadpool(ops.recent.drop, body["id"])
            # queued builds (202) publish from the registry and the worker; these are the direct changes
            op = "deleted" if method == "DELETE" else "registered"
            await run_in_threadpool(ops.publish, op, body["id"])
