"""``POST /localize``: where is the vehicle? Retrieval + landmark matching + RANSAC + re-ranking."""

from __future__ import annotations

import time

from fastapi import APIRouter, Request
from starlette.concurrency import run_in_threadpool

from service.api.deps import StateDep
from service.api.scan_input import read_scan_input, scan_request_body
from service.api.schemas import (
    CandidateResult,
    ErrorResponse,
    LocalizeRequest,
    LocalizeResponse,
    Pose2D,
    RetrievedKeyframe,
)
from service.core.config import MAP_ID_PATTERN

router = APIRouter(tags=["localize"])

_E = {"model": ErrorResponse}


@router.post("/localize", response_model=LocalizeResponse, operation_id="localize",
             responses={400: _E, 404: _E, 409: _E, 413: _E, 415: _E, 422: _E},
             openapi_extra=scan_request_body(LocalizeRequest, {
                 "map_id": {"type": "string", "pattern": MAP_ID_PATTERN, "x-required": True},
                 "top_k": {"type": "integer", "minimum": 1, "maximum": 100}}))
async def localize(request: Request, state: StateDep) -> LocalizeResponse:
    """Localize one scan on a map. JSON ``{map_id, scan_id}`` for a scan uploaded with ``POST /scans``, or
    multipart/form-data with ``map_id`` and a ``scan`` file (Navtech PNG / .npy). ``status`` is
    ``localized`` only when the best candidate has enough RANSAC inliers; ``pose`` is then the query's pose
    in the map frame (metres, degrees)."""
    t0 = time.perf_counter()
    inp = await read_scan_input(request, state, LocalizeRequest, ("map_id", "top_k"))
    map_id = inp.fields["map_id"]
    db = state.registry.ready(map_id)
    config = state.localization_config(inp.fields.get("top_k"))
    result = await run_in_threadpool(db.localize, inp.features, config)
    timings = {**inp.timings_ms, **result.timings_ms}
    state.metrics.observe_stages(timings)
    state.metrics.inc("reradar_localizations_total", status=result.status)
    timings["total_ms"] = (time.perf_counter() - t0) * 1e3
    best = result.best
    keyframe = None
    if best is not None:
        keyframe = RetrievedKeyframe(keyframe_id=best.keyframe_id, timestamp_us=best.timestamp_us,
                                     descriptor_distance=best.descriptor_distance, rank=best.rank,
                                     pose=Pose2D.from_array(best.T_map_keyframe))
    localized = result.status == "localized"
    return LocalizeResponse(
        status=result.status,
        reason=result.reason,
        map_id=map_id,
        scan_id=inp.scan_id,
        pose=Pose2D.from_array(result.T_map_query) if result.T_map_query is not None else None,
        relative_pose=Pose2D.from_array(best.T_keyframe_query)
        if localized and best is not None and best.T_keyframe_query is not None else None,
        keyframe=keyframe,
        num_matches=best.num_matches if best else 0,
        num_inliers=best.num_inliers if best else 0,
        inlier_ratio=best.inlier_ratio if best else 0.0,
        candidates=[CandidateResult(keyframe_id=c.keyframe_id, timestamp_us=c.timestamp_us, rank=c.rank,
                                    descriptor_distance=c.descriptor_distance, num_matches=c.num_matches,
                                    num_inliers=c.num_inliers, inlier_ratio=c.inlier_ratio,
                                    screen_score=c.screen_score, reason=c.reason,
                                    relative_pose=Pose2D.from_array(c.T_keyframe_query)
                                    if c.T_keyframe_query is not None else None)
                    for c in result.candidates],
        timings_ms=timings,
    )
