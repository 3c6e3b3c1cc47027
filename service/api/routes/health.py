"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from fastapi.responses import JSONResponse, PlainTextResponse

from service.api.schemas import HealthResponse, ReadyResponse

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=HealthResponse, operation_id="healthz")
@router.head("/healthz", include_in_schema=False, response_model=HealthResponse)  # load balancers probe with HEAD
def healthz() -> HealthResponse:
    """The process is up (does not check the model or maps)."""
    return HealthResponse()


@router.get("/readyz", response_model=ReadyResponse, operation_id="readyz",
            responses={503: {"model": ReadyResponse, "description": (
                "Model or maps still loading, or maps registered but none ready and none being built "
                "(`reason` says which).")}})
@router.head("/readyz", include_in_schema=False, response_model=ReadyResponse)
def readyz(request: Request) -> Response | ReadyResponse:
    """200 once the model and the maps in the maps directory are loaded and a map can be served; 503 before,
    and while every registered map has failed (none ready, none being built: the replica could answer no
    localization). A service with no map registered is ready: a fresh fleet must take its first upload."""
    state = getattr(request.app.state, "reradar", None)
    if state is None:
        return JSONResponse(ReadyResponse(status="not_ready", reason="the model and the maps are still loading")
                            .model_dump(), status_code=503)
    entries = state.registry.entries()
    ready = sum(e.state == "ready" for e in entries)
    building = sum(e.state == "building" for e in entries)
    reason = None
    if entries and not ready and not building:
        which = "the registered map has" if len(entries) == 1 else f"all {len(entries)} registered maps have"
        reason = (f"no map can be served: {which} failed and none is being built (GET /maps gives each one's "
                  "error); register a map built with the running model, or DELETE /maps/{id} the failed ones")
    answer = ReadyResponse(status="ready" if reason is None else "not_ready", model_id=state.extractor.model_id,
                           weights_sha256=state.extractor.weights_sha256, maps_ready=ready,
                           maps_building=building, maps_total=len(entries), reason=reason)
    if reason is not None:
        return JSONResponse(answer.model_dump(), status_code=503)
    return answer


@router.get("/metrics", response_class=PlainTextResponse, operation_id="metrics",
            responses={200: {"content": {"text/plain": {}}, "description": "Prometheus text format 0.0.4."}})
def metrics(request: Request) -> PlainTextResponse:
    """Request counts, request latencies and pipeline stage timings (Prometheus text format)."""
    state = getattr(request.app.state, "reradar", None)
    if state is None:
        return PlainTextResponse("", media_type="text/plain; version=0.0.4")
    state.metrics.set_gauge("reradar_maps_loaded", state.registry.num_ready)
    state.metrics.set_gauge("reradar_scan_cache_entries", len(state.cache))
    return PlainTextResponse(state.metrics.render(), media_type="text/plain; version=0.0.4")
