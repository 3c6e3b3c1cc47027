"""Builds the FastAPI app. The model and maps load in the lifespan handler, never at import.

Run with ``reradar serve`` or ``uvicorn service.main:app``.
"""

from __future__ import annotations

import fcntl
import gc
import logging
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager, contextmanager
from http import HTTPStatus
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.responses import Response
from starlette.routing import Match

from reradar_core.errors import ModelMismatchError, ReRadarError
from reradar_core.localization.extractor import FeatureExtractor, load_default_extractor
from reradar_core.threads import limit_malloc_arenas
from service.api.middleware import (
    STATIC_METHODS,
    MetricsMiddleware,
    RequestGuardMiddleware,
    leaf_routes,
    static_mount,
)
from service.api.ops_middleware import OpsMiddleware
from service.api.routes import health, localize, maps, scans
from service.api.routes.ui import install_ui
from service.api.security import RequestLimits, build_guard, route_class
from service.core.blas import limit_threads
from service.core.config import Settings
from service.core.errors import (
    PROBLEM_MEDIA_TYPE,
    ServiceError,
    problem_body,
    scrub_paths,
    validation_detail,
)
from service.core.logs import configure_logging
from service.core.metrics import Metrics
from service.core.shared_state import OpsRuntime
from service.core.state import ServiceState

__all__ = ["create_app", "app", "load_served_extractor", "limit_threads", "prepare_process"]

logger = logging.getLogger("service")


@contextmanager
def startup_lock(maps_dir: Path) -> Iterator[None]:
    """Serialise the start-up work on the maps folder (staging clean-up, demo map install, loading) between
    processes of one host: the workers of ``reradar serve --workers N`` all start at once, and one worker's
    clean-up must not remove the demo map another is copying in."""
    maps_dir.mkdir(parents=True, exist_ok=True)
    with open(maps_dir / ".startup.lock", "a+b") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)

API_VERSION = "1.0.0"


def _error_code(exc: ReRadarError) -> str:
    name = type(exc).__name__.removesuffix("Error")
    return "".join("_" + c.lower() if c.isupper() else c for c in name).lstrip("_") or "invalid_input"


#: Error statuses every operation may answer, by route class (documented in the OpenAPI document).
_VEHICLE_ERRORS: tuple[int, ...] = (400, 401, 403, 404, 408, 409, 413, 415, 422, 429, 503)
_OPERATOR_ERRORS: tuple[int, ...] = (400, 401, 403, 404, 408, 409, 413, 415, 422, 429, 503)
_PUBLIC_ERRORS: tuple[int, ...] = (503,)
_HTTP_CODES = {404: "not_found", 405: "method_not_allowed", 400: "bad_request", 413: "payload_too_large"}


def _problem_openapi(doc: dict[str, Any]) -> dict[str, Any]:
    """Document the one error model: every 4xx/5xx response of every operation is
    ``application/problem+json`` with the ``ErrorResponse`` schema; add the statuses the request guard can
    answer, and the ``X-API-Key`` security scheme."""
    problem = {PROBLEM_MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/ErrorResponse"}}}
    comps = doc.setdefault("components", {})
    schemas = comps.setdefault("schemas", {})
    for unused in ("HTTPValidationError", "ValidationError"):
        schemas.pop(unused, None)
    comps["securitySchemes"] = {"ApiKey": {"type": "apiKey", "in": "header", "name": "X-API-Key", "description": (
        "Operator key (RERADAR_API_KEY) for POST/DELETE /maps; a vehicle key (RERADAR_VEHICLE_KEYS) or the "
        "operator key for scans, retrieve and localize (not needed from loopback without vehicle keys).")}}
    for path, ops in doc.get("paths", {}).items():
        for method, op in ops.items():
            kind = route_class(method.upper(), path.replace("{map_id}", "x"))
            extra: tuple[int, ...]
            if kind == "operator":
                op["security"] = [{"ApiKey": []}]
                extra = _OPERATOR_ERRORS
            elif kind == "vehicle":
                op["security"] = [{"ApiKey": []}, {}]
                extra = _VEHICLE_ERRORS
            else:
                extra = _PUBLIC_ERRORS if path not in ("/healthz", "/readyz", "/metrics") else ()
            responses = op.setdefault("responses", {})
            if path.startswith("/maps/{map_id}"):
                extra = tuple(sorted({*extra, 404, 422}))
            for code in extra:
                responses.setdefault(str(code), {})
            for code, resp in responses.items():
                if int(code) < 400 or (path == "/readyz" and code == "503"):
                    continue
                try:
                    phrase = HTTPStatus(int(code)).phrase
                except ValueError:
                    phrase = "Error"
                if not resp.get("description") or resp.get("description") in ("Validation Error", "Additional Response"):
                    resp["description"] = phrase
                resp["content"] = problem
            op["responses"] = dict(sorted(responses.items()))
    return doc


def prepare_process(cfg: Settings) -> None:
    """Process-wide set-up that comes before the model loads: the malloc arena cap (before threads start: the
    request thread pool, and ONNX Runtime's, which starts with the model) and the one log format (the loader logs
    which network runtime it chose). Idempotent: ``reradar serve`` runs it before it loads the model it hands to
    ``create_app`` (``load_served_extractor``), and the lifespan runs it again."""
    if cfg.malloc_arenas:  # docs/OPERATIONS.md, memory
        limit_malloc_arenas(cfg.malloc_arenas)
    configure_logging(cfg.log_level, cfg.log_format)  # ops: one log format


def load_served_extractor(cfg: Settings) -> FeatureExtractor:
    """The descriptor model the service serves (``cfg.model``), loaded exactly as the lifespan would load it
    (``prepare_process`` and ``limit_threads`` first), for a caller that hands it to ``create_app``: ``reradar
    serve`` loads it before the server starts, so that a bad RERADAR_MODEL is one line, and the model is then
    loaded once per process instead of once for that check and again at start-up.

    Raises:
        ReRadarError: unknown model name, missing, unreadable or mismatched weights (or ONNX graph, when
            RERADAR_NETWORK_RUNTIME=onnx asks for it).
    """
    prepare_process(cfg)
    limit_threads(cfg)
    return load_default_extractor(cfg.model)


def create_app(settings: Settings | None = None, extractor: FeatureExtractor | None = None) -> FastAPI:
    """The ReRadar service.

    Args:
        settings: configuration (default: ``Settings()`` from ``RERADAR_*`` environment variables, read when
            the app starts).
        extractor: feature extractor to use (default: ``settings.model``, loaded at startup; ``reradar serve``
            passes the one it loaded with ``load_served_extractor``, so that it is not loaded twice).
    """
    metrics = Metrics()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        cfg = settings or Settings()
        app.state.settings = cfg
        prepare_process(cfg)
        ops = OpsRuntime(cfg)  # ops: shared state (Redis) or in-process
        app.state.ops = ops

        def load() -> ServiceState:
            limit_threads(cfg)
            ext = extractor or load_default_extractor(cfg.model)  # `reradar serve` hands in the one it loaded
            registry = ops.make_registry(ext)  # ops: queued builds with Redis
            with startup_lock(cfg.maps_dir):  # workers of `reradar serve --workers N` start at the same time
                if cfg.load_demo_map:
                    registry.install_demo_map()
                registry.load_all()
            state = ServiceState(cfg, ext, registry, ops.scan_store(), metrics)  # ops: Redis scan store
            state.sessions = ops.session_store()  # ops: tracking sessions in Redis (workers, replicas)
            return state

        state = await run_in_threadpool(load)
        # the model and the loaded maps live as long as the process: keep them out of the cyclic garbage
        # collector's full passes, which otherwise walk every keyframe object (a ~100 ms pause every few dozen
        # requests on a 555-keyframe map; docs/BENCHMARKS.md, "Tail latency")
        gc.collect()
        gc.freeze()
        app.state.guard = build_guard(cfg, spool_dir=state.registry.staging_dir())
        runtime = getattr(state.extractor, "runtime", "torch")  # injected extractors (tests) may not say
        metrics.set_model(state.extractor.model_id, state.extractor.weights_sha256, runtime)  # ops: reradar_model_info
        if not app.state.guard.policy.vehicle_keys:
            logger.info("no RERADAR_VEHICLE_KEYS configured: scans, retrieve and localize answer loopback clients "
                        "only (and callers with the operator key)")
        app.state.reradar = state
        ops.start(state.registry)  # ops: follow other replicas' map changes
        logger.info("ReRadar ready: model %s (network in %s), %d map(s) in %s", state.extractor.model_id,
                    runtime, state.registry.num_ready, cfg.maps_dir)
        try:
            yield
        finally:
            app.state.reradar = None
            app.state.guard = None
            ops.close()
            state.registry.close()

    app = FastAPI(
        title="ReRadar",
        version=API_VERSION,
        summary="Radar global localization as a service: one Navtech scan in, map keyframe and 3-DoF pose out.",
        description=(
            "Units: distances in metres, angles in degrees, times in microseconds (`*_us`) or milliseconds "
            "(`*_ms`). Poses are in the map frame (x, y, counter-clockwise yaw) unless named `relative_*`. "
            "`POST /maps` and `DELETE /maps/{id}` need the operator key in the `X-API-Key` header; scans, "
            "retrieve and localize need a vehicle key (or the operator key) unless the client is on loopback "
            "and no vehicle key is configured. Every error is RFC 9457 `application/problem+json` "
            "(`ErrorResponse`)."
        ),
        lifespan=lifespan,
        docs_url=None,  # ops: /docs and /redoc are served offline by service.api.routes.ui
        redoc_url=None,
    )
    app.state.reradar = None
    app.state.guard = None

    def default_limits() -> RequestLimits:
        cfg: Settings | None = getattr(app.state, "settings", None) or settings
        return RequestLimits.from_settings(cfg or Settings())

    app.add_middleware(RequestGuardMiddleware, get_guard=lambda: app.state.guard, default_limits=default_limits)
    app.add_middleware(MetricsMiddleware, metrics=metrics)
    app.add_middleware(OpsMiddleware)  # ops: recent localizations, map events to other replicas

    def problem(request: Request, status: int, code: str, detail: str, headers: dict[str, str] | None = None,
                errors: list[dict[str, Any]] | None = None) -> Response:
        cfg = getattr(app.state, "settings", None)
        roots = [cfg.maps_dir, cfg.maps_dir.resolve()] if cfg is not None else []
        body = problem_body(status, code, scrub_paths(detail, roots), instance=request.url.path, errors=errors)
        return Response(body, status_code=status, media_type=PROBLEM_MEDIA_TYPE, headers=headers)

    @app.exception_handler(ServiceError)
    async def _service_error(request: Request, exc: ServiceError) -> Response:
        return problem(request, exc.status_code, exc.code, exc.message, exc.headers)

    @app.exception_handler(ModelMismatchError)
    async def _model_mismatch(request: Request, exc: ModelMismatchError) -> Response:
        return problem(request, 409, "model_mismatch", str(exc))

    @app.exception_handler(ReRadarError)
    async def _core_error(request: Request, exc: ReRadarError) -> Response:
        return problem(request, 422, _error_code(exc), str(exc))

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> Response:
        detail, items = validation_detail(exc.errors())
        return problem(request, 422, "validation", detail, errors=items)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> Response:
        code = _HTTP_CODES.get(exc.status_code, f"http_{exc.status_code}")
        detail = f"no endpoint at {request.url.path}; the API is listed at /docs and /openapi.json"
        headers = dict(exc.headers or {})
        if exc.status_code == 405:
            # Starlette's Allow names the methods of the first route on the path only (GET /maps and POST /maps
            # are two routes): list them all
            allowed = sorted({m for route in leaf_routes(app.routes)
                              if route.matches(request.scope)[0] != Match.NONE for m in (route.methods or ())})
            if not allowed and static_mount(request.scope) is not None:  # StaticFiles' 405 names no method
                allowed = list(STATIC_METHODS)
            headers = {k: v for k, v in headers.items() if k.lower() != "allow"}
            headers["Allow"] = ", ".join(allowed)
            detail = f"{request.method} is not allowed on {request.url.path}; allowed: {headers['Allow']}"
        elif exc.status_code != 404 or exc.detail != "Not Found":
            detail = str(exc.detail)
        return problem(request, exc.status_code, code, detail, headers)

    @app.exception_handler(Exception)
    async def _bug(request: Request, exc: Exception) -> Response:
        logger.exception("internal error on %s %s", request.method, request.url.path)
        return problem(request, 500, "internal", "internal server error (logged); please report it")

    for module in (health, maps, scans, localize):
        app.include_router(module.router)
    install_ui(app)  # ops: operator page at /, offline /docs

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = _problem_openapi(get_openapi(
                title=app.title, version=app.version, summary=app.summary, description=app.description,
                routes=app.routes))
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
    return app


app = create_app()
