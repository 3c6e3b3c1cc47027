"""``POST /localize``: where is the vehicle? Retrieval + landmark matching + RANSAC + re-ranking."""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Any

import numpy as np
from fastapi import APIRouter, Request
from starlette.concurrency import run_in_threadpool

from reradar_core.geometry.se2 import wrap_angle
from reradar_core.localization import PosePrior
from service.api.deps import StateDep
from service.api.scan_input import read_scan_input, scan_request_body
from service.api.schemas import (
    CandidateResult,
    ErrorResponse,
    LocalizeRequest,
    LocalizeResponse,
    Pose2D,
    PoseUncertainty,
    RetrievedKeyframe,
)
from service.api.security import caller_of
from service.core.config import MAP_ID_PATTERN
from service.core.errors import BadRequestError
from service.core.ids import SESSION_ID_PATTERN

router = APIRouter(tags=["localize"])

_ODOM = ("odom_dx_m", "odom_dy_m", "odom_dyaw_deg")
_PRIOR = ("prior_x_m", "prior_y_m", "prior_yaw_deg")
_PRIOR_SIGMAS = ("prior_sigma_m", "prior_sigma_yaw_deg")
_FORM_KEYS = ("map_id", "top_k", "session_id", *_ODOM, *_PRIOR, *_PRIOR_SIGMAS)
#: uncertainty of an explicit prior sent without sigmas
_DEFAULT_PRIOR_SIGMA_M = 2.0
_DEFAULT_PRIOR_SIGMA_YAW_DEG = 5.0


def _all_or_none(fields: dict[str, Any], names: tuple[str, ...]) -> bool:
    given = [fields.get(n) is not None for n in names]
    if any(given) and not all(given):
        raise BadRequestError(f"send all of {', '.join(names)} or none of them")
    return all(given)


def _odometry(fields: dict[str, Any]) -> np.ndarray | None:
    """``T_prev_curr`` (x m, y m, yaw rad, wrapped to (-pi, pi]: a turn of 350 degrees is one of -10) from the
    request's odometry, or None.

    Raises:
        BadRequestError: odometry without a ``session_id`` (it moves the session's last pose; alone it would be
            dropped without a word).
    """
    if not _all_or_none(fields, _ODOM):
        return None
    if fields.get("session_id") is None:
        raise BadRequestError("odom_dx_m, odom_dy_m, odom_dyaw_deg move a tracking session's last pose: send them "
                              "with a session_id (or send an explicit prior_x_m, prior_y_m, prior_yaw_deg instead)")
    return np.array([fields["odom_dx_m"], fields["odom_dy_m"], wrap_angle(math.radians(fields["odom_dyaw_deg"]))])


def _prior(fields: dict[str, Any]) -> PosePrior | None:
    """The request's explicit prior, or None."""
    if not _all_or_none(fields, _PRIOR):
        if any(fields.get(n) is not None for n in _PRIOR_SIGMAS):
            raise BadRequestError("prior_sigma_m / prior_sigma_yaw_deg need prior_x_m, prior_y_m, prior_yaw_deg")
        return None
    sigma = fields.get("prior_sigma_m") or _DEFAULT_PRIOR_SIGMA_M
    sigma_yaw = fields.get("prior_sigma_yaw_deg") or _DEFAULT_PRIOR_SIGMA_YAW_DEG
    return PosePrior(np.array([fields["prior_x_m"], fields["prior_y_m"], math.radians(fields["prior_yaw_deg"])]),
                     float(sigma), math.radians(float(sigma_yaw)))

_E = {"model": ErrorResponse}


def _form_number(name: str) -> dict:
    """The OpenAPI schema of a numeric form field: the JSON body's, bounds included (``LocalizeRequest``), so both
    encodings document the same limits (the multipart ones said only "number")."""
    prop = LocalizeRequest.model_json_schema()["properties"][name]
    number = next(b for b in prop.get("anyOf", [prop]) if b.get("type") == "number")
    return {k: v for k, v in {**number, "description": prop.get("description")}.items() if v is not None}


@router.post("/localize", response_model=LocalizeResponse, operation_id="localize",
             responses={400: _E, 404: _E, 409: _E, 413: _E, 415: _E, 422: _E},
             openapi_extra=scan_request_body(LocalizeRequest, {
                 "map_id": {"type": "string", "pattern": MAP_ID_PATTERN, "x-required": True},
                 "top_k": {"type": "integer", "minimum": 1, "maximum": 100},
                 "session_id": {"type": "string", "pattern": SESSION_ID_PATTERN},
                 **{k: _form_number(k) for k in (*_ODOM, *_PRIOR, *_PRIOR_SIGMAS)}}))
async def localize(request: Request, state: StateDep) -> LocalizeResponse:
    """Localize one scan on a map. JSON ``{map_id, scan_id}`` for a scan uploaded with ``POST /scans``, or
    multipart/form-data with ``map_id`` and a ``scan`` file (Navtech PNG / .npy). ``status`` is
    ``localized`` only when enough of the query's landmarks align with the chosen keyframe's (the floor and
    ``min_inliers``) and the confidence reaches its bar (global and tracked answers); ``pose`` is then the query's pose in the
    map frame (metres, degrees). With a ``session_id`` plus odometry, or an explicit ``prior_*``, the scan is tracked from that prior (``mode``
    ``tracking``), falling back to global localization when no consistent pose is found near it; a session
    scan without odometry, or a prior looser than 3 m sigma, is localized globally."""
    t0 = time.perf_counter()
    inp = await read_scan_input(request, state, LocalizeRequest, _FORM_KEYS)
    map_id = inp.fields["map_id"]
    # held while it localizes: a DELETE meanwhile closes the map when this request is done with it
    with state.registry.using(map_id) as db:
        config = state.localization_config(inp.fields.get("top_k"))
        session_id = inp.fields.get("session_id")
        odometry, explicit = _odometry(inp.fields), _prior(inp.fields)  # both validated on every request
        # a session scan without odometry has no prior (the vehicle moved an unknown distance): global; a prior
        # too loose for the registration to reach its error is localized globally by ``Localizer.track`` itself
        # (``TrackingConfig.covers``; docs/SERVICE.md)
        # the session store is Redis in fleet mode: its calls block, so they run in the threadpool, never on the
        # event loop (a hung Redis would stall every request of the replica, health checks included)
        # the scan's time turns the session's odometry into the vehicle's motion (the motion compensation's prior;
        # a scan without a time reads 0, so two of them are no time apart and give none)
        stamp = int(inp.features.timestamp_us)
        # a session is the caller's (its API key: another key's vehicle cannot move it) on this version of the map
        # (a map deleted and registered again under the id has another frame: its sessions start afresh)
        session_key = f"{caller_of(request)}:{session_id}" if session_id else None
        map_key = f"{map_id}@{db.version}"
        # the operator page's record of this answer names the map version too (OpsMiddleware): an answer that
        # finishes after its map was deleted is never shown on a new map registered under the id
        request.scope.setdefault("state", {})["map_version"] = db.version
        moved = (await run_in_threadpool(state.sessions.prior_for, session_key, map_key, odometry, stamp, config.motion)
                 if session_key else None)
        if explicit is not None:  # the scan's time, and the vehicle's own motion whichever pose it starts from
            explicit = replace(explicit, timestamp_us=stamp, twist=None if moved is None else moved.twist)
        prior = explicit or moved
        # a refused global answer looks again in the far view when the map has one (``MapDatabase.localize_views``;
        # a tracked request's global fallback too, ``track_views``)
        if prior is not None:
            answer = await run_in_threadpool(db.track_views, inp.features, prior, inp.far_features, config,
                                             inp.dense_image)
        else:
            answer = await run_in_threadpool(db.localize_views, inp.features, inp.far_features, config,
                                             inp.dense_image)
        result, view = answer.result, answer.view
    if session_key:
        await run_in_threadpool(state.sessions.update, session_key, map_key, result.T_map_query, prior, stamp)
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
        pose_uncertainty=PoseUncertainty.from_array(result.pose_covariance)
        if localized and result.pose_covariance is not None else None,
        motion_compensated=localized and result.motion_compensated,
        keyframe=keyframe,
        num_matches=best.num_matches if best else 0,
        num_inliers=best.num_inliers if best else 0,
        inlier_ratio=best.inlier_ratio if best else 0.0,
        confidence=min(max(float(result.confidence), 0.0), 1.0),
        candidates=[CandidateResult(keyframe_id=c.keyframe_id, timestamp_us=c.timestamp_us, rank=c.rank,
                                    descriptor_distance=c.descriptor_distance, num_matches=c.num_matches,
                                    num_inliers=c.num_inliers, inlier_ratio=c.inlier_ratio,
                                    screen_score=c.screen_score, reason=c.reason,
                                    relative_pose=Pose2D.from_array(c.T_keyframe_query)
                                    if c.T_keyframe_query is not None else None)
                    for c in result.candidates],
        mode=result.mode,
        tracking_lost=result.tracking_lost,
        view=view,
        registration=answer.registration,
        session_id=session_id,
        alignment_score=result.alignment_score,
        timings_ms=timings,
    )
