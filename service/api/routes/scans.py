"""``POST /scans``: upload one scan; its features are computed once and cached under a ``scan_id``."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, File, Form, Request, UploadFile, status
from starlette.concurrency import run_in_threadpool

from service.api.deps import FormDep, StateDep, form_fields
from service.api.scan_input import SCAN_LAYOUT_DESCRIPTION, ClosedFormRoute, read_scan_upload
from service.api.schemas import ErrorResponse, ScanInfo
from service.api.security import caller_of
from service.core.config import MAP_ID_PATTERN
from service.core.errors import BadRequestError, shorten_echo

router = APIRouter(prefix="/scans", tags=["scans"], route_class=ClosedFormRoute)

_ERRORS: dict[int | str, dict[str, Any]] = {400: {"model": ErrorResponse}, 413: {"model": ErrorResponse}, 422: {"model": ErrorResponse}}


@router.post("", response_model=ScanInfo, status_code=status.HTTP_201_CREATED, operation_id="upload_scan",
             responses=_ERRORS)
async def upload_scan(
    request: Request,
    state: StateDep,
    _form: FormDep,
    _fields: Annotated[None, form_fields("scan", "preset", "scan_layout", "map_id", files=("scan",))],
    scan: Annotated[UploadFile, File(description="Navtech polar PNG or .npy array (see scan_layout).")],
    preset: Annotated[str | None, Form(description=(
        "Radar preset (default: the map's, with `map_id`, when the scan fits it; else inferred from the bin "
        "count, a guess where presets of different bin size share it: see `preset_assumed`)."))] = None,
    scan_layout: Annotated[Literal["polar", "navtech"], Form(description=SCAN_LAYOUT_DESCRIPTION)] = "polar",
    map_id: Annotated[str | None, Form(pattern=MAP_ID_PATTERN, description=(
        "The ready map the scan will be localized on: without `preset`, its preset is used where the scan "
        "fits it, as for a scan sent inline."))] = None,
) -> ScanInfo:
    """Decode the scan, compute its global and local features, cache them and return a ``scan_id``."""
    from reradar_core.io.presets import PRESETS

    if preset is not None and preset.lower() not in PRESETS:
        raise BadRequestError(f"unknown preset {shorten_echo(preset)!r}; choose one of {sorted(PRESETS)}")
    if map_id:
        state.registry.ready(map_id)  # 404 / 409 before the upload is read
    data, filename = await read_scan_upload(scan, state.settings.max_scan_pixels, scan_layout)
    timings: dict[str, float] = {}
    features, scan_preset, preset_open, decoded = await run_in_threadpool(
        state.describe_upload, data, filename, preset, timings, scan_layout, map_id or None)
    # the far view's features too while the map (any map, without map_id) has a far-view companion: a request by
    # this scan_id can then look again in the far view as an inline one does (``far_extract_ms``)
    describe_far = state.far_features_of(decoded, timings)
    far = None
    if describe_far is not None and state.registry.serves_far_view(map_id or None):
        far = await run_in_threadpool(describe_far)
    # and its dense image while such a companion holds dense images (the far view's dense registration; the
    # cache keeps no scan to make it from later, ``dense_image_ms``)
    make_dense = state.dense_image_of(decoded, timings)
    dense = None
    if far is not None and make_dense is not None and state.registry.serves_dense(map_id or None):
        dense = await run_in_threadpool(make_dense)
    state.metrics.observe_stages(timings)
    # only this caller can use the scan_id; Redis in fleet mode
    entry = await run_in_threadpool(state.cache.put, features, scan_preset, preset_open, far, caller_of(request),
                                    dense)
    # a guess: left open and not the map's (with map_id the open preset is that map's, checked on use all the same)
    assumed = preset_open and scan_preset != state.map_preset(map_id or None)
    return ScanInfo(scan_id=entry.scan_id, timestamp_us=int(features.timestamp_us), preset=scan_preset,
                    preset_assumed=assumed,
                    num_keypoints=int(features.keypoints_xy_m.shape[0]),
                    descriptor_dim=int(features.global_descriptor.shape[0]),
                    expires_in_s=state.settings.scan_cache_ttl_s, timings_ms=timings)
