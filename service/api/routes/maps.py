"""Map registration, listing, deletion and retrieval (``/maps``)."""

from __future__ import annotations

import shutil
import time
import uuid
from pathlib import Path, PurePosixPath
from typing import Annotated

import numpy as np
from fastapi import APIRouter, File, Form, Request, Response, UploadFile, status
from starlette.concurrency import run_in_threadpool

from maps.paths import far_view_path
from reradar_core.errors import DatasetError, PoseFileError, TimeUnitError
from reradar_core.io.datasets import (
    check_pose_span,
    check_pose_speed,
    check_pose_time_unit,
    mid_sweep_poses_in,
)
from reradar_core.io.poses import TXYYAW_TIME_HEADERS, read_poses
from reradar_core.io.presets import PRESETS, get_preset
from service.api.deps import ApiKeyDep, FormDep, MapIdPath, StateDep, form_fields
from service.api.scan_input import ClosedFormRoute, read_scan_input, scan_request_body
from service.api.schemas import (
    ErrorResponse,
    MapInfo,
    MapList,
    Pose2D,
    RetrievedKeyframe,
    RetrieveRequest,
    RetrieveResponse,
)
from service.core.archive import (
    SCAN_NAME_PATTERN,
    SWEEP_PRESET,
    check_scan_layouts,
    check_scan_times,
    extract_scan_archive,
)
from service.core.config import MAP_ID_PATTERN
from service.core.errors import BadRequestError, PayloadTooLargeError, shorten_echo
from service.core.registry import MapEntry
from service.core.state import ServiceState

router = APIRouter(prefix="/maps", tags=["maps"], route_class=ClosedFormRoute)

_E = {"model": ErrorResponse}



def public_source(source: str | None) -> str | None:
    """A map's ``source`` as the public ``GET /maps`` shows it: the layout and the folder's name, not the build
    machine's path (``boreas:/data/runs/2021-09-02`` -> ``boreas:2021-09-02``; the map file keeps the whole path)."""
    if not source or ":" not in source:
        return source
    kind, _, where = source.partition(":")
    path = where.replace("\\", "/")  # a Windows build machine's path too
    if "/" not in path:
        return source  # no path in it (e.g. upload:archive.zip)
    return f"{kind}:{PurePosixPath(path).name or path}"


def map_info(entry: MapEntry, note: str | None = None) -> MapInfo:
    info = MapInfo(id=entry.map_id, state=entry.state, progress=entry.progress, error=entry.error, note=note,
                   scans_done=entry.scans_done, scans_total=entry.scans_total,
                   registered_utc=entry.registered_utc,
                   # served with a companion; while building, whether the build makes one
                   far_view=(entry.db.far is not None) if entry.db is not None else (entry.state == "building"
                                                                                     and entry.far_view))
    if entry.db is not None:
        m = entry.db.metadata
        info.num_keyframes = len(entry.db)
        info.model_id, info.weights_sha256 = m.model_id, m.weights_sha256
        info.radar_preset, info.descriptor_dim = m.radar_preset, m.descriptor_dim
        info.created_utc, info.source = m.created_utc, public_source(m.source)
        info.index_kind = entry.db.index.kind
        info.pose_time = m.pose_time  # type: ignore[assignment]  # the store checks it is one of the two
        info.place_repetition = ("stored" if entry.db.repetition_adopted
                                 else "other_settings" if entry.db.repetition_stored else "not_stored")
        # computed once per map and settings (vectorized: ~0.03 s for 100,000 keyframes), then cached
        info.keyframes_motion_known = int(entry.db.localizer.keyframe_twists()[1].sum())
    return info


@router.get("", response_model=MapList, operation_id="list_maps")
def list_maps(state: StateDep) -> MapList:
    """All registered maps with their state."""
    data = [map_info(e, state.registry.build_note(e)) for e in state.registry.entries()]
    return MapList(data=data, count=len(data))


@router.get("/{map_id}", response_model=MapInfo, operation_id="get_map", responses={404: _E, 422: _E})
def get_map(state: StateDep, map_id: MapIdPath) -> MapInfo:
    """One map's state, build progress and metadata."""
    entry = state.registry.get(map_id)
    return map_info(entry, state.registry.build_note(entry))


def _save_upload(upload: UploadFile, target: Path, limit: tuple[int, str] | None = None) -> int:
    """Copy ``upload`` to ``target``; its size in bytes. ``limit``: (most bytes, what to say) beyond which it is a
    ``PayloadTooLargeError`` with that message."""
    size = 0
    upload.file.seek(0)
    with open(target, "wb") as out:
        while chunk := upload.file.read(1 << 20):
            size += len(chunk)
            if limit is not None and size > limit[0]:
                raise PayloadTooLargeError(limit[1])
            out.write(chunk)
    return size


def _declared_time_unit(pose_path: Path) -> str | None:
    """The time unit a t,x,y,yaw CSV's header names (``t_s`` -> ``s``), else None (``t``, no header, or
    another format, whose unit is its own or follows from absolute values)."""
    with pose_path.open(encoding="utf-8-sig", errors="replace") as fh:
        head = fh.readline().split(",")[0].strip().lower()
    return TXYYAW_TIME_HEADERS.get(head)


def _register(state: ServiceState, map_id: str, map_file: UploadFile | None, archive: UploadFile | None,
              poses: UploadFile | None, preset: str | None, far_view: bool = False,
              far_map_file: UploadFile | None = None) -> tuple[MapEntry, bool]:
    registry = state.registry
    registry.validate_id(map_id)
    registry.path_for(map_id)
    if (map_file is None) == (archive is None):
        raise BadRequestError("send either 'map_file' (a prebuilt .h5 map) or 'archive' + 'poses' (scans to build from)")
    if map_file is not None:
        if poses is not None:
            raise BadRequestError("'poses' goes with 'archive', not with 'map_file'")
        if preset is not None:  # it would be ignored: a map file records the preset it was built with
            raise BadRequestError("'preset' applies to a scan 'archive' (the preset of its scans); a prebuilt "
                                  "'map_file' carries its own preset: leave 'preset' out")
        if far_view:  # a prebuilt map's companion is built already: it comes as a file
            raise BadRequestError("'far_view' asks a scan 'archive' build for a far-view companion; a prebuilt "
                                  "'map_file' comes with its companion as 'far_map_file' (the <map>.far.h5 of "
                                  "`reradar build-map --far-view`)")
        if far_map_file is not None:
            registry.check_far_view_served("far_map_file")  # before anything is stored
        staged = registry.staging_dir() / f"{uuid.uuid4().hex}.h5"
        far_staged = far_view_path(staged) if far_map_file is not None else None
        try:
            if _save_upload(map_file, staged) == 0:
                raise BadRequestError("the uploaded map file is empty")
            if far_map_file is not None and far_staged is not None and _save_upload(far_map_file, far_staged) == 0:
                raise BadRequestError("the uploaded far-view map file ('far_map_file') is empty")
        except BaseException:
            staged.unlink(missing_ok=True)
            if far_staged is not None:
                far_staged.unlink(missing_ok=True)
            raise
        return registry.register_file(map_id, staged, far_staged), False
    if far_map_file is not None:
        raise BadRequestError("'far_map_file' goes with a prebuilt 'map_file'; an 'archive' build makes its own "
                              "far-view companion with 'far_view=true'")
    if poses is None:
        raise BadRequestError("'archive' needs a 'poses' file (Boreas radar_poses.csv, MulRan global_pose.csv or t,x,y,yaw CSV)")
    if far_view:
        registry.check_far_view_served("far_view")  # before the archive is unpacked
    if preset is not None and preset.lower() not in PRESETS:
        raise BadRequestError(f"unknown preset {shorten_echo(preset)!r}; choose one of {sorted(PRESETS)}")
    preset = None if preset is None else preset.lower()  # the map records the preset's name (QA session 40: "BOREAS")
    # early check so a large archive is not unpacked for a taken id; start_build re-checks atomically
    registry.check_free(map_id)
    work = registry.staging_dir() / f"job-{uuid.uuid4().hex}"
    work.mkdir()
    try:
        arch = work / "archive.bin"
        _save_upload(archive, arch)  # type: ignore[arg-type]
        scan_paths = extract_scan_archive(arch, work / "scans", state.settings.max_archive_scans,
                                          state.settings.max_map_upload_bytes * 4, state.settings.max_scan_pixels)
        arch.unlink()
        # a copy of a PNG under another name carries the original's time, by which the map keys its keyframes, and
        # a PNG whose name (at which its pose is taken below) and embedded time are two instants would get the pose
        # of one and the time of the other: refused here (400) rather than after the whole build (each PNG's first
        # row only: ~0.03 ms a scan; a disagreement is confirmed by decoding that one scan as the build would)
        check_scan_times(scan_paths, get_preset(preset or SWEEP_PRESET),
                         lambda path: registry.decoded_scan_time_us(path, preset),
                         lambda path: registry.scan_refusal(path, preset))
        # one radar layout, one the build reads (each header's first bytes, one scan decoded), before minutes of build
        check_scan_layouts(scan_paths, lambda path: registry.scan_refusal(path, preset))
        pose_path = work / "poses.csv"
        most = state.settings.max_pose_file_bytes
        _save_upload(poses, pose_path, (most, (
            f"the 'poses' file is larger than RERADAR_MAX_POSE_FILE_MB ({state.settings.max_pose_file_mb:g} MB): send the poses at the "
            "scans' rate or near it (a Boreas applanix/radar_poses.csv, ~0.15 MB per hour), not a high-rate log")))
        try:
            track = read_poses(pose_path).sorted()  # a binary file is a PoseFileError there
        except TimeUnitError as exc:  # the library's advice names command-line options: say what works here
            raise PoseFileError(f"poses file: {exc.problem}; name the time column by its unit in a header line "
                                "(t_s, t_ms, t_us or t_ns, e.g. `t_s,x,y,yaw`), or send absolute UTC times") from None
        if len(track) < 1:
            raise PoseFileError("poses upload holds no poses")
        # names are checked against MAX_SCAN_TIMESTAMP_US by extract_scan_archive, so they fit int64
        stamps = np.array([int(SCAN_NAME_PATTERN.match(p.name).group(1)) for p in scan_paths],  # type: ignore[union-attr]
                          dtype=np.int64)
        # the same rules as a sequence folder's (load_sequence): times read in a unit 1000x off (a header naming
        # another unit than its values': every keyframe collapsed onto the drive's first metres, QA session 23)
        try:
            check_pose_time_unit(track, stamps, _declared_time_unit(pose_path), "the uploaded poses file",
                                 how="name the time column t_{unit} in the header line")
            check_pose_speed(track, "the uploaded poses file",
                             how="named by the time column's header: t_s, t_ms, t_us or t_ns")
        except DatasetError as exc:
            raise PoseFileError(str(exc)) from None
        try:
            check_pose_span(track, stamps, [f"scan {p.name}" for p in scan_paths], "the uploaded poses file",
                            "; scan files must be named by their timestamp in microseconds")
        except DatasetError as exc:
            raise BadRequestError(str(exc)) from None
        # keyframe poses at mid-sweep (docs/CONVENTIONS.md); every preset sweeps 400 azimuths at 4 Hz
        pose_arr = mid_sweep_poses_in(track, stamps, get_preset(preset or SWEEP_PRESET))
        entry = state.registry.start_build(map_id, scan_paths, pose_arr, preset, work,
                                           source=f"upload:{archive.filename or 'archive'}",  # type: ignore[union-attr]
                                           far_view=far_view, pose_track=track)
        return entry, True
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise


@router.post("", response_model=MapInfo, status_code=status.HTTP_201_CREATED, operation_id="register_map",
             responses={202: {"model": MapInfo, "description": "Build job started; poll GET /maps/{id}."},
                        400: _E, 401: _E, 409: _E, 413: _E, 415: _E, 422: _E})
def register_map(
    state: StateDep,
    _auth: ApiKeyDep,
    _form: FormDep,
    _fields: Annotated[None, form_fields("map_id", "map_file", "archive", "poses", "preset", "far_view",
                                         "far_map_file", files=("map_file", "archive", "poses", "far_map_file"))],
    response: Response,
    map_id: Annotated[str, Form(pattern=MAP_ID_PATTERN, description="New map id.")],
    map_file: Annotated[UploadFile | None, File(description="A prebuilt HDF5 map (docs/MAP_FORMAT.md).")] = None,
    archive: Annotated[UploadFile | None, File(description="zip/tar(.gz) of <timestamp_us>.png|.npy scans.")] = None,
    poses: Annotated[UploadFile | None, File(description="Pose file covering the scans' timestamps.")] = None,
    preset: Annotated[str | None, Form(description="Radar preset of the archive's scans.")] = None,
    far_view: Annotated[bool, Form(description=(
        "With 'archive': also build the map's far-view companion from the same scans and poses (as `reradar "
        "build-map --far-view`; the far pass costs about as much again as the map's), served with the map for the answers "
        "its own view refuses (docs/MODEL.md, 'The far view'). 400 where the service serves no far view."))] = False,
    far_map_file: Annotated[UploadFile | None, File(description=(
        "With 'map_file': its far-view companion (the <map>.far.h5 of `reradar build-map --far-view`), checked "
        "against the map's keyframes (422 and nothing registered when it does not hold them) and served with it. "
        "400 where the service serves no far view."))] = None,
) -> MapInfo:
    """Register a route database: upload a prebuilt map (201, ready; with its far-view companion if sent) or a
    scan archive + poses (202: the map, and with ``far_view`` its far-view companion, is built in the background;
    poll ``GET /maps/{id}``). Needs the API key."""
    entry, building = _register(state, map_id, map_file, archive, poses, preset, far_view, far_map_file)
    if building:
        response.status_code = status.HTTP_202_ACCEPTED
    return map_info(entry, state.registry.build_note(entry))


@router.delete("/{map_id}", response_model=MapInfo, operation_id="delete_map",
               responses={401: _E, 404: _E, 409: _E, 422: _E})
def delete_map(state: StateDep, _auth: ApiKeyDep, map_id: MapIdPath) -> MapInfo:
    """Unregister a map and delete its file. Needs the API key."""
    return map_info(state.registry.delete(map_id))


@router.post("/{map_id}/retrieve", response_model=RetrieveResponse, operation_id="retrieve",
             responses={400: _E, 404: _E, 409: _E, 413: _E, 415: _E, 422: _E},
             openapi_extra=scan_request_body(RetrieveRequest, {
                 "top_k": {"type": "integer", "minimum": 1, "maximum": 100}}))
async def retrieve(request: Request, state: StateDep, map_id: MapIdPath) -> RetrieveResponse:
    """Top-k keyframes of the map by global descriptor, for a cached ``scan_id`` (JSON) or an inline scan
    (multipart)."""
    t0 = time.perf_counter()
    state.registry.ready(map_id)  # 404 / 409 before the upload is read
    inp = await read_scan_input(request, state, RetrieveRequest, ("top_k",), map_id)
    k = inp.fields.get("top_k") or state.settings.localization.top_k
    t1 = time.perf_counter()
    with state.registry.using(map_id) as db:  # a DELETE meanwhile closes the map once this is done with it
        hits = await run_in_threadpool(db.retrieve, inp.features.global_descriptor, k)
    timings = dict(inp.timings_ms)
    timings["retrieve_ms"] = (time.perf_counter() - t1) * 1e3
    state.metrics.observe_stages(timings)
    timings["total_ms"] = (time.perf_counter() - t0) * 1e3
    return RetrieveResponse(
        map_id=map_id, scan_id=inp.scan_id, timings_ms=timings,
        keyframes=[RetrievedKeyframe(keyframe_id=h.keyframe_id, timestamp_us=h.timestamp_us,
                                     descriptor_distance=h.descriptor_distance, rank=h.rank,
                                     pose=Pose2D.from_array(h.T_map_keyframe)) for h in hits],
    )
