"""Request and response models. Angles in degrees, distances in metres, times in us/ms (field names say so);
poses are in the map frame unless the field is named ``relative_*``."""

from __future__ import annotations

import math
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from reradar_core.bounds import MAX_ABS_COORDINATE_M
from service.core.ids import MAP_ID_PATTERN, SESSION_ID_PATTERN

__all__ = [
    "ErrorResponse",
    "Problem",
    "ValidationItem",
    "Pose2D",
    "HealthResponse",
    "ReadyResponse",
    "MapInfo",
    "MapList",
    "ScanInfo",
    "ScanRef",
    "RetrieveRequest",
    "RetrievedKeyframe",
    "RetrieveResponse",
    "LocalizeRequest",
    "CandidateResult",
    "LocalizeResponse",
]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ValidationItem(BaseModel):
    """One invalid request field."""

    loc: list[str | int] = Field(description="Where: e.g. [\"body\", \"top_k\"].")
    msg: str
    type: str


class ErrorResponse(BaseModel):
    """Every error body: RFC 9457 problem details (`application/problem+json`), docs/SERVICE.md."""

    type: str = Field(description="URI of the problem type, `urn:reradar:error:<error>`.")
    title: str = Field(description="HTTP status phrase.")
    status: int = Field(ge=400, le=599, description="HTTP status code.")
    detail: str = Field(description="What is wrong and what to do.")
    error: str = Field(description="Machine-readable error code, e.g. `scan_format`, `not_found`.")
    instance: str | None = Field(default=None, description="Request path.")
    errors: list[ValidationItem] | None = Field(default=None, description="Invalid fields (validation errors).")


#: The same model under its RFC name.
Problem = ErrorResponse


class Pose2D(_Model):
    """A 3-DoF pose: position in metres, heading in degrees counter-clockwise from the frame's +x, in (-180, 180]."""

    x_m: float
    y_m: float
    yaw_deg: float = Field(description="Heading, degrees counter-clockwise from the frame's +x, in (-180, 180].")

    @classmethod
    def from_array(cls, pose: np.ndarray) -> Pose2D:
        """From (x m, y m, yaw rad); the heading wrapped to (-180, 180] degrees."""
        # as ``geometry.se2.wrap_angle``, which this module (imported by the light vehicle-side client) cannot import
        yaw = math.fmod(float(pose[2]) + math.pi, 2.0 * math.pi)
        yaw = (yaw + 2.0 * math.pi if yaw < 0.0 else yaw) - math.pi
        return cls(x_m=float(pose[0]), y_m=float(pose[1]), yaw_deg=math.degrees(math.pi if yaw == -math.pi else yaw))


class PoseUncertainty(_Model):
    """How precise a localized pose is: its covariance in the map frame, in the API's units."""

    covariance: list[Annotated[list[float], Field(min_length=3, max_length=3)]] = Field(
        min_length=3, max_length=3, description=(
        "3 x 3 covariance of the pose (rows and columns x_m, y_m, yaw_deg; entries m^2, m deg, deg^2; map frame), "
        "row-major, symmetric. From the final registration's landmark pairs (a street lined on one side only is "
        "loose along it), scaled by factors fitted on training data so that 95 % of right answers' position errors "
        "lie inside its 95 % ellipse and 95 % of their heading errors inside its 95 % interval (docs/MODEL.md, Pose "
        "covariance: measured coverage per kind of drive). The matched keyframe's own map pose is taken as exact."))
    sigma_x_m: float = Field(description="Standard deviation of x, metres (sqrt of covariance[0][0]).")
    sigma_y_m: float = Field(description="Standard deviation of y, metres (sqrt of covariance[1][1]).")
    sigma_yaw_deg: float = Field(description="Standard deviation of the heading, degrees (sqrt of covariance[2][2]).")

    @classmethod
    def from_array(cls, cov: np.ndarray) -> PoseUncertainty:
        """From a (3, 3) covariance of (x m, y m, yaw rad): the heading's rows and columns turned into degrees."""
        scale = np.array([1.0, 1.0, math.degrees(1.0)])
        c = np.asarray(cov, np.float64).reshape(3, 3) * np.outer(scale, scale)
        return cls(covariance=[[float(v) for v in row] for row in c], sigma_x_m=math.sqrt(max(c[0, 0], 0.0)),
                   sigma_y_m=math.sqrt(max(c[1, 1], 0.0)), sigma_yaw_deg=math.sqrt(max(c[2, 2], 0.0)))


class HealthResponse(_Model):
    status: Literal["ok"] = "ok"


class ReadyResponse(_Model):
    """`GET /readyz`: 200 `ready` once the model and the maps folder are loaded and a map can be served (or none
    is registered yet, so a fresh fleet can take its first upload); 503 `not_ready` with a `reason` while
    loading, or when maps are registered but none is ready and none is being built."""

    status: Literal["ready", "not_ready"]
    model_id: str | None = None
    weights_sha256: str | None = None
    maps_ready: int = 0
    maps_building: int = Field(default=0, description="Maps being built (queued or running).")
    maps_total: int = 0
    reason: str | None = Field(default=None, description="Why the service is not ready (503 only).")


class MapInfo(_Model):
    """A registered map and its state."""

    id: str = Field(description="Map id (also the file name `<id>.h5`).")
    state: Literal["ready", "building", "failed"]
    progress: float = Field(ge=0, le=1, description="Build progress, fraction of scans described.")
    num_keyframes: int = 0
    scans_done: int = Field(default=0, description=(
        "Scan descriptions made so far by the build (with `far_view`, the far view's follow the map's); a `ready` "
        "map: its keyframes."))
    scans_total: int = Field(default=0, description=(
        "Scan descriptions the build makes: the archive's scans, twice with `far_view` (once in each view; a far "
        "one costs about as much again as the map's); a `ready` map: its keyframes."))
    error: str | None = Field(default=None, description="Why building or loading failed.")
    note: str | None = Field(default=None, description=(
        "While `building`: why the build may not be progressing (e.g. no map-build worker is running), or, with "
        "every scan described (`progress` 1), that it is measuring where the map repeats itself before it is ready."))
    model_id: str | None = None
    weights_sha256: str | None = None
    radar_preset: str | None = None
    descriptor_dim: int | None = None
    index_kind: str | None = Field(default=None, description="FAISS index type: flat (exact), hnsw or ivf.")
    created_utc: str | None = None
    registered_utc: str
    source: str | None = Field(default=None, description=(
        "What the map was built from: the dataset layout and the folder's name (`boreas:2021-09-02`; the build "
        "machine's path stays in the map file), or `upload:<archive name>`."))
    pose_time: Literal["mid_sweep", "first_azimuth"] | None = Field(default=None, description=(
        "Which instant of each keyframe scan the map's poses - and so the poses answered on this map - refer to: "
        "`mid_sweep` (every map written since 2026-11-30; docs/CONVENTIONS.md), or `first_azimuth` for an older map "
        "without the attribute: its answers are the first-azimuth pose, up to ~1 m behind the mid-sweep pose at "
        "driving speed (rebuild it with `reradar build-map` or `POST /maps`)."))
    keyframes_motion_known: int | None = Field(default=None, ge=0, description=(
        "Keyframes whose motion on the map drive is known under this service's localization settings (a keyframe "
        "within `max_keyframe_gap_s`, 2 s, of it in time, and a plausible drive between them): answers on the others "
        "keep the rigid registration's pose, not motion-compensated (docs/CONVENTIONS.md 'Motion compensation'). "
        "Fewer than `num_keyframes` on a map whose scans are over 2 s apart, or whose times are not the drive's."))
    far_view: bool = Field(default=False, description=(
        "`true`: the map is served with its far-view companion (`<id>.far.h5`, from `POST /maps` with `far_view=true` "
        "or `far_map_file`, or `reradar build-map --far-view`): an answer its own view refuses is looked at again in "
        "the far view (`view: far`; docs/SERVICE.md, 'The far view'); while `building`, that the build also builds "
        "one. `false`: no companion, or none served (`RERADAR_FAR_VIEW=false`, or one that does not fit the map)."))
    place_repetition: Literal["stored", "other_settings", "not_stored"] | None = Field(default=None, description=(
        "Where the repeated-place check (an answer on a keyframe whose place repeats on the map is `ambiguous`) "
        "reads each keyframe's place repetition: `stored` in the map under this service's localization settings "
        "(every map built since 2026-12-03 under them: maps this service builds are), `other_settings` (stored under "
        "other settings) or `not_stored` (an older map, or one built with `--no-place-repetition`): in the last two "
        "cases each keyframe's is measured when it first wins, 20-40 ms once per keyframe and process (`reradar "
        "map-repetition MAP.h5` stores it under the default settings; a map built by this service, under its own)."))


class MapList(_Model):
    data: list[MapInfo]
    count: int


class ScanInfo(_Model):
    """An uploaded scan whose features are cached."""

    scan_id: str
    timestamp_us: int
    preset: str | None
    preset_assumed: bool = Field(default=False, description=(
        "No preset was given and none followed from the scan or `map_id`: `preset` is a guess (3,360 range bins "
        "fit boreas, boreas-2021 and mulran; a polar .npy carries no geometry). A scan uploaded without `preset` "
        "whose preset such a scan leaves open (a guess, or `map_id`'s) is refused (422) on a map of another range "
        "geometry; upload it with `preset`, or with the `map_id` it is for."))
    num_keypoints: int
    descriptor_dim: int
    expires_in_s: float
    timings_ms: dict[str, float]


class ScanRef(_Model):
    """Requests by reference. JSON bodies are validated strictly: `top_k` must be a JSON integer (not `true`,
    `"5"`, `5.5` or `NaN`)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    scan_id: str = Field(min_length=1, max_length=64, description="Id returned by POST /scans.")


class RetrieveRequest(ScanRef):
    """Retrieve by reference (JSON). Inline scans use multipart/form-data: `scan` file, optional `top_k`,
    `preset`."""

    top_k: int | None = Field(default=None, ge=1, le=100, description="Keyframes to return (default: service top_k).")


class RetrievedKeyframe(_Model):
    keyframe_id: int
    timestamp_us: int
    descriptor_distance: float = Field(description="Euclidean distance between unit global descriptors, [0, 2].")
    rank: int
    pose: Pose2D = Field(description="Keyframe pose in the map frame, at the keyframe scan's mid-sweep time.")


class RetrieveResponse(_Model):
    map_id: str
    scan_id: str | None
    keyframes: list[RetrievedKeyframe]
    timings_ms: dict[str, float]


class LocalizeRequest(ScanRef):
    """Localize by reference (JSON). Inline scans use multipart/form-data: `map_id` field, `scan` file,
    optional `top_k`, `preset` and the tracking fields below.

    Tracking mode (docs/SERVICE.md): send a `session_id` (the server keeps the session's last pose on this
    map) and, when known, the odometry since the session's previous scan (`odom_*`, in the previous scan's
    frame); or an explicit prior (`prior_*`). Without either, or when tracking is lost, the scan is localized
    globally."""

    map_id: str = Field(pattern=MAP_ID_PATTERN)
    top_k: int | None = Field(default=None, ge=1, le=100, description=(
        "Candidates retrieved and screened (default: service top_k; the best verify_k are verified in full)."))
    session_id: str | None = Field(default=None, pattern=SESSION_ID_PATTERN, description=(
        "Tracking session: the server remembers this session's last pose (per map, expires after "
        "RERADAR_SESSION_TTL_S) and tracks from it."))
    odom_dx_m: float | None = Field(default=None, allow_inf_nan=False, ge=-1000, le=1000, description=(
        "Odometry since the session's previous scan: forward motion in that scan's frame, metres."))
    odom_dy_m: float | None = Field(default=None, allow_inf_nan=False, ge=-1000, le=1000,
                                    description="Odometry: leftward motion, metres.")
    odom_dyaw_deg: float | None = Field(default=None, allow_inf_nan=False, ge=-360, le=360,
                                        description="Odometry: heading change, degrees CCW.")
    prior_x_m: float | None = Field(default=None, allow_inf_nan=False, ge=-MAX_ABS_COORDINATE_M,
                                    le=MAX_ABS_COORDINATE_M, description="Explicit prior: map-frame x, metres.")
    prior_y_m: float | None = Field(default=None, allow_inf_nan=False, ge=-MAX_ABS_COORDINATE_M,
                                    le=MAX_ABS_COORDINATE_M, description="Explicit prior: map-frame y, metres.")
    prior_yaw_deg: float | None = Field(default=None, allow_inf_nan=False, ge=-360, le=360,
                                        description="Explicit prior: heading, degrees.")
    prior_sigma_m: float | None = Field(default=None, allow_inf_nan=False, gt=0, le=1000, description=(
        "Explicit prior: position standard deviation, metres (default 2); over 3 the scan is localized globally."))
    prior_sigma_yaw_deg: float | None = Field(default=None, allow_inf_nan=False, gt=0, le=180, description=(
        "Explicit prior: heading standard deviation, degrees (default 5); over 5 (a heading not known to "
        "within 10 degrees) the scan is localized globally."))


class CandidateResult(_Model):
    """Geometric verification of one retrieved candidate."""

    keyframe_id: int
    timestamp_us: int
    rank: int
    descriptor_distance: float
    num_matches: int
    num_inliers: int
    inlier_ratio: float
    screen_score: float | None = Field(default=None, description=(
        "Fraction of query landmarks aligned by the cheap landmark-alignment screen, 0-1 (null if not screened); "
        "for a candidate of a deeper search round outside that round's best prescreen_keep (5), the coarse "
        "prescreen's fraction (every (N // 64)-th of the N query landmarks paired, 1,000 minimal sets)."))
    reason: str | None = Field(default=None, description=(
        "Why this candidate gave no pose: screened_out (not among the best verify_k), too_few_inliers, ..."))
    relative_pose: Pose2D | None = Field(default=None, description="Query pose in the keyframe's sensor frame.")


class LocalizeResponse(_Model):
    """Where the vehicle is. `pose` is set only when `status` is `localized`."""

    status: Literal["localized", "not_localized"]
    reason: str | None = Field(default=None, description=(
        "Why not localized: no_candidate, too_few_matches, too_few_inliers (under 12 aligned landmarks or under "
        "the aligned-ratio floor fitted with the confidence model: min_aligned_ratio in its JSON, 45 % of the "
        "query's landmarks), ambiguous (a "
        "rival pose aligns as many landmarks, or a keyframe at another place, over 20 m from the answer, screens "
        "within 7.5 % of the query's landmarks of the winner: localization.min_place_margin, or the winning "
        "keyframe's place repeats on the map: another place aligns 95 % of what its own does, "
        "localization.max_place_repetition), low_confidence (below "
        "min_confidence). A "
        "failed tracking attempt (a registration below the bar or outside the prior's gate) falls back to global "
        "localization: reason and candidates are then the global answer's, with tracking_lost true."))
    map_id: str
    scan_id: str | None
    pose: Pose2D | None = Field(default=None, description=(
        "Query pose in the map frame (keyframe pose o relative pose) at the scan's mid-sweep time: its first "
        "azimuth's timestamp + 124.7 ms at 4 Hz (the antenna turns while the vehicle moves; a registration of "
        "whole sweeps aligns their mid-sweep poses)."))
    relative_pose: Pose2D | None = Field(default=None, description="Query pose in the matched keyframe's sensor frame.")
    pose_uncertainty: PoseUncertainty | None = Field(default=None, description=(
        "How precise `pose` is (its covariance and standard deviations), when localized; null otherwise, or when "
        "too few landmarks pair at the final pose to say. `confidence` says whether the pose is right, this how "
        "close: for fusing the answer with odometry."))
    motion_compensated: bool = Field(default=False, description=(
        "`pose` is motion-compensated (both sweeps de-skewed, the vehicle's motion fitted with the pose; docs/"
        "CONVENTIONS.md, Motion compensation); false: the rigid registration's pose (compensation off, the "
        "keyframe's motion on the map unknown, or the fit discarded), whose `pose_uncertainty` is scaled for that."))
    keyframe: RetrievedKeyframe | None = Field(default=None, description="The keyframe the query was registered to.")
    num_matches: int = 0
    num_inliers: int = 0
    inlier_ratio: float = 0.0
    confidence: float = Field(default=0.0, ge=0.0, le=1.0, description=(
        "Probability in [0, 1] that `pose` (or, when not localized, the best candidate's pose) is within the "
        "success thresholds (20 m and 10 deg urban, 25 m off-road): a logistic model over the answer's cues "
        "(aligned-landmark ratio and count, margin over a different place, descriptor distance, landmark "
        "spread, agreement of the top candidates, pose ambiguity), fitted on training data only "
        "(docs/MODEL.md, Confidence). `localized` requires it to reach the configured min_confidence; "
        "0 when there is no pose. The checks after it (a place that fits twice, a tie between places: reason "
        "`ambiguous`) do not lower it, so read a refused answer's confidence together with its `reason`."))
    candidates: list[CandidateResult] = Field(default_factory=list)
    mode: Literal["global", "tracking"] = Field(default="global", description=(
        "`tracking`: registered from the session's / the request's prior; `global`: retrieval + re-ranking."))
    tracking_lost: bool = Field(default=False, description=(
        "A prior was given but no consistent pose was found near it; this is the global answer."))
    view: Literal["near", "far"] = Field(default="near", description=(
        "`far`: the map's own view refused and this is the far view's answer (the same network on the radar's "
        "whole range, from the map's far-view companion written by `reradar build-map --far-view`; global answers "
        "and a tracked request's global fallback, for inline scans and scans uploaded while a map had a "
        "companion); `near`: the map's own view (docs/MODEL.md, 'The far view')."))
    registration: Literal["landmarks", "dense"] = Field(default="landmarks", description=(
        "How the pose was found: `landmarks` (the paper's landmark matching, either view), or `dense`: both views "
        "refused a scan with little in view and the far view's whole-image correlation placed it (inline scans, "
        "and scans uploaded while such a map was loaded, on a map whose far-view companion holds dense images, "
        "`reradar build-map --far-view` since 2026-12-04; "
        "`num_matches` and `num_inliers` are then 0, `pose_uncertainty` is the dense answers' calibrated one, "
        "and `confidence` is the "
        "dense registration's own calibrated probability; docs/MODEL.md, 'Dense registration')."))
    session_id: str | None = None
    alignment_score: float = Field(default=0.0, description=(
        "Fraction of the query's landmarks aligned with the keyframe's (0-1); `localized` needs at least the "
        "fitted floor (45 %), `min_inliers` and `confidence` at the bar. Not a calibrated probability."))
    timings_ms: dict[str, float]
