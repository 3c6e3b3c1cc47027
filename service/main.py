"""Builds the FastAPI app. The model and maps load in the lifespan handler, never at import.

Run with ``reradar serve`` or ``uvicorn service.main:app``.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool

from reradar_core.errors import ModelMismatchError, ReRadarError
from reradar_core.localization.extractor import FeatureExtractor, load_default_extractor
from service.api.middleware import BodyLimitMiddleware, MetricsMiddleware
from service.api.ops_middleware import OpsMiddleware
from service.api.routes import health, localize, maps, scans
from service.api.routes.ui import install_ui
from service.core.blas import limit_blas_threads
from service.core.config import Settings
from service.core.errors import ServiceError
from service.core.logs import configure_logging
from service.core.metrics import Metrics
from service.core.shared_state import OpsRuntime
from service.core.state import ServiceState

__all__ = ["create_app", "app"]

logger = logging.getLogger("service")

API_VERSION = "1.0.0"


def _error(status: int, detail: str, code: str) -> JSONResponse:
    return JSONResponse({"detail": detail, "error": code}, status_code=status)


def _error_code(exc: ReRadarError) -> str:
    name = type(exc).__name__.removesuffix("Error")
    return "".join("_" + c.lower() if c.isupper() else c for c in name).lstrip("_") or "invalid_input"


def create_app(settings: Settings | None = None, extractor: FeatureExtractor | None = None) -> FastAPI:
    """The ReRadar service.

    Args:
        settings: configuration (default: ``Settings()`` from ``RERADAR_*`` environment variables, read when
            the app starts).
        extractor: feature extractor to use (default: the shipped ``DescriptorExtractor``, loaded at startup).
    """
    metrics = Metrics()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        cfg = settings or Settings()
        app.state.settings = cfg
        configure_logging(cfg.log_level, cfg.log_format)  # ops: one log format
        ops = OpsRuntime(cfg)  # ops: shared state (Redis) or in-process
        app.state.ops = ops

        def load() -> ServiceState:
            import torch

            torch.set_num_threads(cfg.torch_threads)
            limit_blas_threads(cfg.blas_threads)
            ext = extractor or load_default_extractor(cfg.model)
            registry = ops.make_registry(ext)  # ops: queued builds with Redis
            if cfg.load_demo_map:
                registry.install_demo_map()
            registry.load_all()
            return ServiceState(cfg, ext, registry, ops.scan_store(), metrics)  # ops: Redis scan store

        state = await run_in_threadpool(load)
        metrics.set_model(state.extractor.model_id, state.extractor.weights_sha256)  # ops: reradar_model_info
        app.state.reradar = state
        ops.start(state.registry)  # ops: follow other replicas' map changes
        logger.info("ReRadar ready: model %s, %d map(s) in %s", state.extractor.model_id,
                    state.registry.num_ready, cfg.maps_dir)
        try:
            yield
        finally:
            app.state.reradar = None
            ops.close()
            state.registry.close()

    app = FastAPI(
        title="ReRadar",
        version=API_VERSION,
        summary="Radar global localization as a service: one Navtech scan in, map keyframe and 3-DoF pose out.",
        description=(
            "Units: distances in metres, angles in degrees, times in microseconds (`*_us`) or milliseconds "
            "(`*_ms`). Poses are in the map frame (x, y, counter-clockwise yaw) unless named `relative_*`. "
            "Mutating endpoints (`POST /maps`, `DELETE /maps/{id}`) need the `X-API-Key` header."
        ),
        lifespan=lifespan,
        docs_url=None,  # ops: /docs and /redoc are served offline by service.api.routes.ui
        redoc_url=None,
    )
    app.state.reradar = None

    def limit_for(method: str, path: str) -> int:
        cfg: Settings | None = getattr(app.state, "settings", None) or settings
        if cfg is None:
            cfg = Settings()
        if method == "POST" and path.rstrip("/") == "/maps":
            return cfg.max_map_upload_bytes
        return cfg.max_upload_bytes

    app.add_middleware(BodyLimitMiddleware, limit_for=limit_for)
    app.add_middleware(MetricsMiddleware, metrics=metrics)
    app.add_middleware(OpsMiddleware)  # ops: recent localizations, map events to other replicas

    @app.exception_handler(ServiceError)
    async def _service_error(request: Request, exc: ServiceError) -> JSONResponse:
        return _error(exc.status_code, exc.message, exc.code)

    @app.exception_handler(ModelMismatchError)
    async def _model_mismatch(request: Request, exc: ModelMismatchError) -> JSONResponse:
        return _error(409, str(exc), "model_mismatch")

    @app.exception_handler(ReRadarError)
    async def _core_error(request: Request, exc: ReRadarError) -> JSONResponse:
        return _error(422, str(exc), _error_code(exc))

    @app.exception_handler(Exception)
    async def _bug(request: Request, exc: Exception) -> JSONResponse:
        logger.exception("internal error on %s %s", request.method, request.url.path)
        return _error(500, "internal server error (logged); please report it", "internal")

    for module in (health, maps, scans, localize):
        app.include_router(module.router)
    install_ui(app)  # ops: operator page at /, offline /docs
    return app


app = create_app()
