"""The operator page (``/``), its data endpoints (``/ui/api/...``) and the API docs served offline.

Every asset ships in the package: the page from ``service/ui/``, Swagger UI and ReDoc from the
``fastapi-offline`` package (FastAPI's default ``/docs`` loads them from a CDN and is blank offline). These
routes are for people, so they stay out of the OpenAPI schema.
"""

from __future__ import annotations

import functools
import re
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, FastAPI, Query, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import FileResponse, HTMLResponse, Response
from fastapi.staticfiles import StaticFiles
from starlette.concurrency import run_in_threadpool

from reradar_core.geometry.se2 import wrap_angle
from service.api.deps import MapIdPath, StateDep, VehicleDep

__all__ = ["install_ui", "router", "UI_DIR", "MAX_TRAJECTORY_POINTS"]

UI_DIR = Path(__file__).resolve().parents[2] / "ui"
#: Keyframes drawn at most; longer trajectories are subsampled evenly (the last keyframe is kept).
MAX_TRAJECTORY_POINTS = 5000
#: Records read beyond ``limit`` for the latest localizations, in place of those of an earlier map version.
_STALE_SLACK = 32

router = APIRouter(include_in_schema=False)


def _swagger_dir() -> Path:
    import fastapi_offline

    return Path(fastapi_offline.__file__).resolve().parent / "static"


#: A source-map comment on a line of its own (``/*# sourceMappingURL=... */`` in CSS, ``//# ...`` in JS).
_SOURCE_MAP_LINE = re.compile(rb"^[ \t]*(?:/\*# sourceMappingURL=[^\n]*\*/|//# sourceMappingURL=[^\n]*)[ \t]*$\n?",
                              re.MULTILINE)


@functools.lru_cache(maxsize=8)
def _without_source_map(path: str, mtime_ns: int) -> bytes:
    """The file's bytes without its source-map comment lines (cached per file version)."""
    return _SOURCE_MAP_LINE.sub(b"", Path(path).read_bytes())


class VendorFiles(StaticFiles):
    """fastapi-offline's Swagger UI / ReDoc assets, served without their ``sourceMappingURL`` comments: the package
    ships no ``.map`` files, so every browser with its developer tools open asked for one and logged a 404."""

    async def get_response(self, path: str, scope) -> Response:
        response = await super().get_response(path, scope)
        if response.status_code != 200 or not isinstance(response, FileResponse) or \
                not str(response.path).endswith((".css", ".js")):
            return response
        stat = Path(response.path).stat()
        body = _without_source_map(str(response.path), stat.st_mtime_ns)
        keep = {k: v for k, v in response.headers.items() if k in ("etag", "last-modified")}
        return Response(body, media_type=response.media_type, headers=keep)


@router.get("/", response_class=FileResponse)
@router.head("/", include_in_schema=False, response_class=FileResponse)  # uptime monitors probe with HEAD
def operator_page() -> FileResponse:
    return FileResponse(UI_DIR / "index.html", media_type="text/html")


@router.get("/docs", response_class=HTMLResponse)
def swagger_ui(request: Request) -> HTMLResponse:
    return get_swagger_ui_html(openapi_url=request.app.openapi_url, title=f"{request.app.title} - API docs",
                               swagger_js_url="/ui/vendor/swagger-ui-bundle.js",
                               swagger_css_url="/ui/vendor/swagger-ui.css",
                               swagger_favicon_url="/ui/static/favicon.svg",
                               oauth2_redirect_url="/docs/oauth2-redirect")


@router.get("/docs/oauth2-redirect", response_class=HTMLResponse)
def swagger_ui_redirect() -> HTMLResponse:
    return get_swagger_ui_oauth2_redirect_html()


@router.get("/redoc", response_class=HTMLResponse)
def redoc(request: Request) -> HTMLResponse:
    return get_redoc_html(openapi_url=request.app.openapi_url, title=f"{request.app.title} - API reference",
                          redoc_js_url="/ui/vendor/redoc.standalone.js", redoc_favicon_url="/ui/static/favicon.svg",
                          with_google_fonts=False)


def trajectory_points(poses: np.ndarray, max_points: int = MAX_TRAJECTORY_POINTS) -> np.ndarray:
    """Indices of the keyframes to draw: all of them up to ``max_points``, else an even subsample that keeps
    the first and the last. ``poses`` (N, 3) float64 ``T_map_keyframe`` (x m, y m, yaw rad)."""
    n = int(poses.shape[0])
    if n <= max_points:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_points).round().astype(np.int64))


@router.get("/ui/api/maps/{map_id}/trajectory")
def map_trajectory(state: StateDep, _auth: VehicleDep, map_id: MapIdPath) -> dict[str, Any]:
    """Keyframe positions of a ready map in the map frame: ``x_m``, ``y_m`` (metres), ``yaw_deg``. Access as
    the vehicle routes (``service.api.security``): a vehicle or operator key, or a loopback client while no
    vehicle key is configured."""
    db = state.registry.ready(map_id)
    poses = np.asarray(db.map.poses, dtype=np.float64)
    keep = trajectory_points(poses)
    p = poses[keep]
    return {"map_id": map_id, "num_keyframes": int(poses.shape[0]), "keyframe_ids": keep.tolist(),
            "x_m": np.round(p[:, 0], 3).tolist(), "y_m": np.round(p[:, 1], 3).tolist(),
            "yaw_deg": _wrapped_deg(np.round(np.degrees(wrap_angle(p[:, 2])), 2)).tolist()}


def _wrapped_deg(deg: np.ndarray) -> np.ndarray:
    """Headings in degrees wrapped to (-180, 180] (the API's range), e.g. after rounding -179.9999 to -180.0."""
    out = np.asarray(deg, np.float64)  # wrapped in radians before rounding: only the ends move, values stay exact
    return np.where(out <= -180.0, out + 360.0, np.where(out > 180.0, out - 360.0, out))


@router.get("/ui/api/maps/{map_id}/localizations")
async def map_localizations(request: Request, state: StateDep, _auth: VehicleDep, map_id: MapIdPath,
                            limit: Annotated[int, Query(ge=1, le=1000)] = 50) -> dict[str, Any]:
    """The latest localizations on ``map_id``, newest first (map frame, metres, degrees; 503 when they live in
    an unreachable Redis; 404 for an unknown map, as every map route). Access as ``map_trajectory``: these are
    vehicles' positions."""
    entry = state.registry.get(map_id)
    recent = request.app.state.ops.recent
    # answers recorded for another version of the map (in flight when it was deleted and registered anew) are
    # not this map's: a few of them at most, so a little more is read than shown
    version = entry.db.version if entry.db is not None else None
    data = await run_in_threadpool(recent.latest, map_id, limit + _STALE_SLACK)
    data = [{k: v for k, v in r.items() if k != "map_version"} for r in data
            if version is not None and r.get("map_version") == version][:limit]
    return {"map_id": map_id, "data": data, "count": len(data)}


def install_ui(app: FastAPI) -> None:
    """Add the operator page, its assets and the offline API docs to ``app`` (built with ``docs_url=None,
    redoc_url=None``)."""
    app.include_router(router)
    app.mount("/ui/static", StaticFiles(directory=UI_DIR), name="ui-static")
    app.mount("/ui/vendor", VendorFiles(directory=_swagger_dir()), name="ui-vendor")
