"""The registry of maps served: ``<maps_dir>/<map_id>.h5`` files, loaded maps, and background build jobs.

Invariants: a map file appears under its final name only when complete (uploads are validated in a hidden
staging folder, fsync'ed and renamed; builds use the atomic ``MapWriter``); a failed upload or build never
touches another map; map ids match ``MAP_ID_PATTERN`` and resolved paths must stay inside ``maps_dir``.

Nothing accepted is lost: before ``POST /maps`` answers 202 the build has a job record
``<maps_dir>/.jobs/<map_id>.json`` on disk (fsync'ed). The record is removed once the map file is installed,
rewritten as ``failed`` with the reason when the build fails, and a record still ``building`` when the service
starts means the process died mid-build: the map is then reported ``failed`` with that reason, never unknown.
"""

from __future__ import annotations

import datetime as _dt
import errno
import json
import logging
import math
import os
import re
import shutil
import threading
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np

from maps.arrays import prune_arrays
from maps.build import build_map
from maps.database import FAR_VIEW, MapDatabase, far_view_mismatch
from maps.paths import DEMO_MAP_PATH, FAR_VIEW_SUFFIX, far_view_path
from maps.store import (
    KeyframeMap,
    MapMetadata,
    fsync_dir,
    install_file,
    open_map,
    probe_map,
    read_metadata,
    remove_stale_temp_files,
)
from reradar_core.errors import (
    ConfigError,
    MapFormatError,
    ModelMismatchError,
    ReRadarError,
    ScanFormatError,
    ScanTooLargeError,
)
from reradar_core.geometry.cartesian import CartesianConfig
from reradar_core.io.poses import PoseSequence
from reradar_core.io.scan import (
    RadarScan,
    check_header_size,
    load_scan_bytes,
    max_scan_file_bytes,
    preset_bin_sizes,
    presets_with_bins,
    range_bins_ambiguous,
    scan_header,
)
from reradar_core.localization.extractor import FeatureExtractor
from reradar_core.localization.far_view import FarViewConfig
from reradar_core.matching.dense import dense_image_settings
from reradar_core.retrieval import IndexConfig
from service.core.archive import (
    SCAN_NAME_PATTERN,
    duplicate_scan_time_message,
    pose_file_reader,
    scan_name_time_message,
)
from service.core.config import MAP_ID_PATTERN, Settings
from service.core.errors import BadRequestError, ConflictError, NotFoundError, ServiceError, scrub_paths

__all__ = ["MapEntry", "MapRegistry", "MapState", "DEMO_MAP_ID", "FileIdentity", "build_failure_message",
           "file_identity", "install_map_files", "map_name_taken", "UPLOAD_CHECK_NOTE", "refuse_delete_of_upload_in_check"]

logger = logging.getLogger(__name__)

MapState = Literal["ready", "building", "failed"]
DEMO_MAP_ID = "demo"
#: left in ``maps_dir`` by ``DELETE /maps/demo``: the demo map is not installed again at the next start
DEMO_DELETED_MARKER = ".demo-deleted"
_ID_RE = re.compile(MAP_ID_PATTERN)
_STAGING = ".staging"
_JOBS = ".jobs"
#: ``<maps_dir>/.verified/<map_id>.json``: the ``FileIdentity`` of a map file read through in a child process
#: (``probe_map``) or installed by an upload that was: opened in-process without another probe
_VERIFIED = ".verified"


def build_failure_message(exc: BaseException) -> str:
    """What a failed build reports (``GET /maps/{id}``): the message alone for an input error (``ReRadarError``,
    ``ServiceError``, ``ValueError``, ``OSError``: it says what is wrong, e.g. ``1600000018000000.png: ...``); the class name before
    the message of anything else (a bug, whose message alone may be ``'key'``)."""
    text = str(exc)
    if isinstance(exc, ReRadarError | ServiceError | ValueError | OSError) and text:  # ServiceError: e.g. the id
        return text  # taken meanwhile (QA session 41: "ConflictError: map 'cc' already exists; ...")
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


#: what tells one map file from another under the same name: (st_dev, st_ino, st_size, st_mtime_ns)
FileIdentity = tuple[int, int, int, int]


def file_identity(path: Path) -> FileIdentity | None:
    """``path``'s ``FileIdentity``, None when it does not exist. A map file is only ever replaced by another
    inode (``install_file`` renames or links a new file in), and the old inode cannot be reused while a
    registry holds it open, so a changed identity means another file."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns


def map_name_taken(path: Path) -> bool:
    """A file, or a link (a dangling one too: ``os.link`` fails on its name, so no map can be installed there), is
    at ``path``."""
    return path.exists() or path.is_symlink()


def install_map_files(built: Path, target: Path, far_built: Path | None = None) -> None:
    """Install the complete map file ``built`` as ``target`` and its far-view companion ``far_built`` (None: the map
    comes without one) as ``far_view_path(target)``.

    The map is the commit point: it is installed exclusively (``install_file(exclusive=True)``: never over an
    existing map), and only the writer whose map that is then puts its companion under the final name, over
    whatever lies there. So of two writers of one map id on a shared maps folder at the same moment (no upload
    claim: Redis down), the one whose map is installed has its own companion beside it, and the other leaves
    nothing. The steps:

    1. a map file ``target`` exists: ``FileExistsError``, nothing touched;
    2. the companion is hard-linked under its final name when that name is free (``far_built`` stays): a process
       that opens the map as soon as it appears (another replica) finds it beside it;
    3. the map is installed (the commit);
    4. the companion is moved under its final name, replacing whatever lies there: a companion without its map
       (left by an install or a delete that was stopped midway; logged) or another writer's from step 2. A map
       without a companion removes such a file instead (logged): a registration serves only the companion it
       brings, never one it finds.

    A failed or cancelled install leaves nothing of this call installed, and ``built`` and ``far_built`` in place:
    before the commit its own companion is taken off the final name (anything else found there is put back),
    after it (step 4 failed) the map is moved back to ``built`` too.

    Raises:
        FileExistsError: a map file ``target`` exists (or appeared meanwhile).
        ConflictError: ``far_built`` is given and a folder lies under the companion's name (put there by hand: no
            file can replace it); nothing touched.
    """
    far_target = far_view_path(target)
    if map_name_taken(target):
        raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), str(target))
    if far_built is not None and far_target.is_dir() and not far_target.is_symlink():
        raise ConflictError(f"a folder named {far_target.name} lies in the maps folder where the far-view companion "
                            f"of map {target.stem!r} goes; an operator must remove it, then register the map again")
    own: FileIdentity | None = None
    linked = False
    if far_built is not None:
        with open(far_built, "rb+") as fh:  # durable before any name points to it
            os.fsync(fh.fileno())
        own = file_identity(far_built)  # a hard link or a rename keeps it
        linked = _link_if_free(far_built, far_target)
    map_identity = file_identity(built)
    try:
        install_file(built, target, exclusive=True)
    except BaseException:
        if linked:
            _take_own_back(far_target, own)
        raise
    try:
        if far_built is not None:
            if not linked and (far_target.exists() or far_target.is_symlink()):
                logger.warning("%s: a far-view companion that lay there without its map (left by an install or a "
                               "delete stopped midway) is replaced by the one installed with map %s", far_target.name,
                               target.stem)
            os.replace(far_built, far_target)  # a no-op where step 2 linked it: the same file
            far_built.unlink(missing_ok=True)
        elif far_target.exists() or far_target.is_symlink():
            logger.warning("%s: a far-view companion that lay there without its map (left by an install or a delete "
                           "stopped midway) is removed: map %s is installed without one", far_target.name, target.stem)
            try:
                far_target.unlink()
            except FileNotFoundError:
                pass
            except OSError as exc:  # a folder under the companion's name: it is not served (``_attach_far``)
                logger.warning("%s: not removed (%s)", far_target.name, exc.strerror)
        fsync_dir(target.parent)
    except BaseException:  # undo the commit: nothing of this call stays installed
        if file_identity(target) == map_identity:
            os.replace(target, built)
        if far_built is not None:
            if far_built.exists():  # not moved yet: only the link of step 2 (if any) to take back
                if linked:
                    _take_own_back(far_target, own)
            elif file_identity(far_target) == own:
                os.replace(far_target, far_built)
        fsync_dir(target.parent)
        raise


def _link_if_free(src: Path, dst: Path) -> bool:
    """Hard-link ``src`` as ``dst`` when no file has that name (atomic); False when one has, or where the file system
    has no hard links (the companion is then installed after its map only)."""
    try:
        os.link(src, dst)
    except OSError:
        return False
    fsync_dir(dst.parent)
    return True


def _take_own_back(far_target: Path, own: FileIdentity | None) -> None:
    """Take this install's companion (``FileIdentity`` ``own``) off its final name ``far_target``, never another
    writer's: whatever lies there is first renamed to a unique name (atomic), then deleted when it is this
    install's, else put back, unless the name was taken meanwhile (by the writer whose map is installed, installing
    its own companion)."""
    aside = far_target.with_name(f".{far_target.name}.{uuid.uuid4().hex}.taken")
    try:
        os.rename(far_target, aside)
    except FileNotFoundError:
        return
    if file_identity(aside) != own:
        try:
            os.link(aside, far_target)
        except FileExistsError:
            pass
        except OSError:  # no hard links here: a check and a rename
            if not (far_target.exists() or far_target.is_symlink()):
                os.replace(aside, far_target)
    aside.unlink(missing_ok=True)
    fsync_dir(far_target.parent)


#: UTC time format of the registry's and the build records' timestamps (``registered_utc``, ``created_utc``, ...)
RECORD_TIME_FORMAT = "%Y-%m-%dT%H:%M:%SZ"


def utc_now() -> str:
    """Now, UTC, in ``RECORD_TIME_FORMAT``."""
    return _dt.datetime.now(_dt.UTC).strftime(RECORD_TIME_FORMAT)


@dataclass
class MapEntry:
    """One registered map and its state (``ready``, ``building`` or ``failed`` with ``error``).

    ``file_id``: the ``file_identity`` of the map file this entry opened (None for a build in progress or a
    failed build, which have none): ``MapSync`` reopens the map when the file under its name changes.
    ``far_view``: a build in progress also builds the map's far-view companion (``start_build(far_view=True)``);
    whether a ready map is served with one is ``db.far``. ``uploaded``: an uploaded map file being checked and
    installed (``building`` without a build job)."""

    map_id: str
    path: Path
    state: MapState
    db: MapDatabase | None = None
    error: str | None = None
    scans_done: int = 0
    scans_total: int = 0
    registered_utc: str = field(default_factory=utc_now)
    file_id: FileIdentity | None = None
    far_view: bool = False
    #: a prebuilt map file sent with ``POST /maps`` (``register_file``), ``building`` while it is checked and
    #: installed (seconds; there is no build job to wait for or cancel)
    uploaded: bool = False

    @property
    def progress(self) -> float:
        if self.state == "ready":
            return 1.0
        return self.scans_done / self.scans_total if self.scans_total else 0.0


def _same_view(metadata: MapMetadata, view: CartesianConfig) -> bool:
    """The map of ``metadata`` was described on the Cartesian image ``view`` (side px, m/px)."""
    return (metadata.cartesian_width_px == int(view.width_px)
            and math.isclose(metadata.cartesian_resolution_m, float(view.resolution_m), rel_tol=1e-9))


def _far_marker_id(path: Path) -> str:
    """The name a far-view companion's ``FileIdentity`` is recorded under in ``.verified`` (``x.far.h5`` ->
    ``x.far``: no map id has a dot)."""
    return path.name[: -len(".h5")]


def _log_far_served(path: Path, db: MapDatabase) -> None:
    """Log that the far-view companion ``path`` is served with the map of ``db`` (attached: ``db.far``)."""
    far = db.far
    stored = far.map.dense_settings if far is not None else None
    dense = ("with dense images" if db.far_dense else
             "without dense images (rebuild it with `reradar build-map --far-view` for the dense registration)"
             if stored is None else
             "with dense images of other settings (not used; rebuild it)"
             if stored != dense_image_settings(FAR_VIEW.dense) else
             "whose dense images are unreadable (not used; rebuild it)")
    logger.info("%s: far view served with map %s (%d keyframes, %s)", path.name, db.map.path.stem,
                len(far) if far is not None else 0, dense)


#: what a map whose uploaded file is being checked is doing (``MapEntry.uploaded``)
UPLOAD_CHECK_NOTE = ("the uploaded map file is being checked and installed (no build job; it is ready or refused "
                     "within seconds)")


def refuse_delete_of_upload_in_check(entry: MapEntry) -> None:
    """``ConflictError`` for a DELETE of a map whose uploaded file is still being checked (``MapEntry.uploaded``):
    there is no build job to cancel, it settles within seconds."""
    if entry.state == "building" and entry.uploaded:
        raise ConflictError(f"map {entry.map_id!r}: {UPLOAD_CHECK_NOTE}; retry the DELETE then")


def last_pass_note(entry: MapEntry) -> str | None:
    """What a ``building`` entry does while its progress stands still between its scan descriptions, so that it is
    not read as stuck: with every scan described (``progress`` 1), measuring where the map repeats itself before the
    install; a build with its far-view companion (``far_view``: ``scans_total`` 2 N) also at N (``progress``
    0.5), where the map's own place-repetition pass runs before the far view's descriptions begin. None otherwise."""
    if entry.state == "building" and entry.uploaded:
        return UPLOAD_CHECK_NOTE
    if entry.state != "building" or not entry.scans_total:
        return None
    repetition = "the build is measuring where the map repeats itself (20-40 ms per keyframe and thread)"
    if entry.far_view and entry.scans_total % 2 == 0 and entry.scans_done == entry.scans_total // 2:
        return (f"every scan is described in the map's own view; {repetition}, then describes every scan again in "
                "the far view (the second half of the progress)")
    if entry.scans_done < entry.scans_total:
        return None
    if entry.far_view:
        return ("every scan is described in both views; the build is measuring where the far-view companion "
                "repeats itself (20-40 ms per keyframe and thread) and then installs the map with it")
    return f"every scan is described; {repetition} and then installs the map"


class MapRegistry:
    """Thread-safe registry; one background worker builds maps from uploaded scan archives."""

    def __init__(self, settings: Settings, extractor: FeatureExtractor) -> None:
        self.settings = settings
        self.extractor = extractor
        self.maps_dir = settings.maps_dir.resolve()
        self.maps_dir.mkdir(parents=True, exist_ok=True)
        self.index_config = IndexConfig(kind=settings.index_kind, exact_max_size=settings.index_exact_max_size)
        self._entries: dict[str, MapEntry] = {}
        self._lock = threading.RLock()
        #: requests localizing on each map right now (``using``), and the maps let go of (deleted, dropped or
        #: replaced) while some were: closed when the last of them finishes (``_let_go``)
        self._holders: dict[MapDatabase, int] = {}
        self._retired: set[MapDatabase] = set()
        self._closed = False  # close() ran: a folder pass finishing late must not add an open map
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="map-build")
        # ReRadar's far view (the same weights on the radar's whole range) for maps with a far-view companion
        self.far_extractor: FeatureExtractor | None = None
        if settings.far_view and hasattr(extractor, "with_view"):
            self.far_extractor = extractor.with_view(FarViewConfig().cartesian)

    @property
    def far_view_enabled(self) -> bool:
        """Maps are served with their far-view companions here (``RERADAR_FAR_VIEW`` and a model that can
        describe the far view: ``far_extractor``)."""
        return self.far_extractor is not None

    def check_far_view_served(self, field_name: str) -> None:
        """Refuse a registration asking for a far-view companion (form field ``field_name``) where none would be
        served (``far_view_enabled``).

        Raises:
            BadRequestError: saying why and what to send instead.
        """
        if self.far_view_enabled:
            return
        why = ("its far view is switched off (RERADAR_FAR_VIEW=false)" if not self.settings.far_view
               else f"its model {self.extractor.model_id!r} cannot describe the far view")
        raise BadRequestError(f"{field_name!r} asks for a far-view companion, but this service serves none: {why}; "
                              f"register the map without {field_name!r}")

    # ---- paths and ids -------------------------------------------------------------------------------------
    def validate_id(self, map_id: str) -> str:
        if not isinstance(map_id, str) or not _ID_RE.fullmatch(map_id):
            raise BadRequestError(
                f"invalid map id {map_id!r}: use 1-64 lower-case letters, digits, '_' or '-', "
                f"starting with a letter or digit"
            )
        return map_id

    def path_for(self, map_id: str) -> Path:
        """``<maps_dir>/<map_id>.h5``, the name itself: a symbolic link there is the map's file as the link (as at
        start-up), never resolved to its target, so that a DELETE removes the link and not another map's file it
        points to, and a link out of the folder is served rather than refused (QA session 41: the folder pass
        stopped on one; DELETE of a link to another map deleted that map's file)."""
        self.validate_id(map_id)
        path = self.maps_dir / f"{map_id}.h5"
        if path.parent != self.maps_dir:  # defence in depth; the id's pattern already forbids this
            raise BadRequestError(f"map id {map_id!r} names a file outside the maps directory")
        return path

    def staging_dir(self) -> Path:
        d = self.maps_dir / _STAGING
        d.mkdir(exist_ok=True)
        return d

    # ---- durable job records -------------------------------------------------------------------------------
    def _job_path(self, map_id: str) -> Path:
        return self.maps_dir / _JOBS / f"{map_id}.json"

    def _write_job(self, entry: MapEntry, source: str | None = None) -> None:
        """Write ``entry``'s job record durably (temporary file, fsync, rename, fsync folder)."""
        path = self._job_path(entry.map_id)
        path.parent.mkdir(exist_ok=True)
        record = {"map_id": entry.map_id, "state": entry.state, "error": entry.error,
                  "scans_total": entry.scans_total, "registered_utc": entry.registered_utc,
                  "source": source, "far_view": entry.far_view, "pid": os.getpid()}
        tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.part")
        tmp.write_text(json.dumps(record))
        install_file(tmp, path)

    def _drop_job(self, map_id: str) -> None:
        path = self._job_path(map_id)
        if path.exists():
            path.unlink(missing_ok=True)
            fsync_dir(path.parent)

    def _load_jobs(self) -> None:
        """Register the maps whose build failed or was cut short by a crash, from their job records."""
        jobs = self.maps_dir / _JOBS
        if not jobs.is_dir():
            return
        for part in jobs.glob(".*.part"):
            part.unlink(missing_ok=True)
        for path in sorted(jobs.glob("*.json")):
            map_id = path.stem
            try:
                record = json.loads(path.read_text())
            except (OSError, ValueError):
                record = {}
            if not _ID_RE.fullmatch(map_id):
                continue
            if (self.maps_dir / f"{map_id}.h5").exists():
                self._drop_job(map_id)  # built and installed; the process stopped before dropping the record
                continue
            entry = MapEntry(map_id, self.maps_dir / f"{map_id}.h5", "failed",
                             scans_total=int(record.get("scans_total") or 0),
                             registered_utc=str(record.get("registered_utc") or utc_now()))
            if record.get("state") == "failed" and record.get("error"):
                entry.error = str(record["error"])
            else:
                entry.error = ("the service stopped (crash or restart) while this map was being built, and the "
                               f"uploaded scans are gone: DELETE /maps/{map_id} and register it again")
                self._write_job(entry, record.get("source"))
                logger.error("map %s: build interrupted by a stop of the service; marked failed", map_id)
            with self._lock:
                self._entries[map_id] = entry

    # ---- loading -------------------------------------------------------------------------------------------
    def _load_entry(self, map_id: str, path: Path) -> MapEntry:
        """Open the map file ``path`` as an entry: ``ready`` with its keyframes, or ``failed`` with the reason;
        either with the file's identity (``MapEntry.file_id``)."""
        # before opening: a file replaced in between then differs from the identity and is reopened later
        entry = MapEntry(map_id, path, "failed", file_id=file_identity(path))
        try:
            self._probe_unverified(map_id, path, entry.file_id)
            entry.db = self._open(path)
            entry.state = "ready"
            entry.scans_total = entry.scans_done = len(entry.db)
        except (MapFormatError, ModelMismatchError, OSError) as exc:
            entry.error = scrub_paths(str(exc), [self.maps_dir])  # public (GET /maps/{id}): no server folders
        return entry

    # ---- map files not yet read through: a crafted file must not take the service down ----------------------
    def _verified_marker(self, map_id: str) -> Path:
        return self.maps_dir / _VERIFIED / f"{map_id}.json"

    def _is_verified(self, map_id: str, identity: FileIdentity) -> bool:
        try:
            return tuple(json.loads(self._verified_marker(map_id).read_text())["identity"]) == identity
        except (OSError, ValueError, KeyError, TypeError):
            return False

    def _mark_verified(self, map_id: str, identity: FileIdentity | None) -> None:
        """Record that the file of ``identity`` was read through (atomically; best effort: without the record
        the file is probed again next time)."""
        if identity is None:
            return
        marker = self._verified_marker(map_id)
        tmp = marker.parent / f".{map_id}.{uuid.uuid4().hex}.tmp"
        try:
            marker.parent.mkdir(exist_ok=True)
            tmp.write_text(json.dumps({"identity": list(identity)}))
            os.replace(tmp, marker)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            logger.warning("map %s: could not record that its file was checked (%s); it is checked again next time",
                           map_id, exc)

    def _probe_unverified(self, map_id: str, path: Path, identity: FileIdentity | None) -> None:
        """Read a map file this service has not read through before (one placed straight into the maps folder,
        or built or replaced by another process) in a child process first (``probe_map``), as uploads are: a
        crafted file that crashes or hangs the HDF5 library then fails this map, not the service. Files already
        read through (same ``FileIdentity``) are not probed again.

        Raises:
            MapFormatError: the child refused the file, crashed on it or timed out.
        """
        if identity is None or self._is_verified(map_id, identity):
            return
        try:
            probe_map(path)
        except RuntimeError as exc:  # the check itself could not run (no child process): open as before
            logger.warning("map %s: its file could not be checked in a child process (%s); opening it directly",
                           map_id, exc)
            return
        self._mark_verified(map_id, identity)

    def check_compatible(self, metadata: MapMetadata, path: Path, extractor: FeatureExtractor | None = None) -> None:
        """Refuse a map whose descriptors cannot be compared with those of ``extractor`` (default: the running
        model; ``far_extractor`` for a far-view companion): another global descriptor length D, another local
        descriptor length C (where the extractor states it: ``local_dim``), or another view (the Cartesian image
        its keyframes were described on, px and m/px: the far view has the near one's weights, so the weights hash
        alone does not tell a companion from its map). Such a map would load and then fail every localization.

        Raises:
            MapFormatError: naming the map's and the model's lengths or views.
        """
        ext = extractor or self.extractor
        view = getattr(ext, "cartesian", None)  # the FeatureExtractor protocol's; a test double may lack it
        if view is not None and not _same_view(metadata, view):
            if extractor is not None:
                hint = ("it is no far-view companion: send the <map>.far.h5 that `reradar build-map --far-view` "
                        "writes beside the map")
            elif _same_view(metadata, FarViewConfig().cartesian):
                hint = ("it is a far-view companion (`reradar build-map --far-view` writes it as <map>.far.h5): "
                        "register it together with its map ('far_map_file'), not as a map")
            else:
                hint = "rebuild the map with this model"
            raise MapFormatError(
                f"{path}: the map's keyframes were described on a {metadata.cartesian_width_px} px image at "
                f"{metadata.cartesian_resolution_m:g} m/px, but {ext.model_id!r} describes "
                f"{int(view.width_px)} px at {float(view.resolution_m):g} m/px: their descriptors are not comparable; "
                f"{hint}")
        dim = int(ext.descriptor_dim)
        if metadata.descriptor_dim != dim:
            raise MapFormatError(
                f"{path}: the map's global descriptors have {metadata.descriptor_dim} values (descriptor_dim) but "
                f"the running model {ext.model_id!r} computes {dim}; rebuild the map with this model")
        local_dim = getattr(ext, "local_dim", None)  # not part of the FeatureExtractor protocol (test fakes)
        if local_dim is not None and metadata.local_descriptor_dim != int(local_dim):
            raise MapFormatError(
                f"{path}: the map's local descriptors have {metadata.local_descriptor_dim} values "
                f"(local_descriptor_dim) but the running model {ext.model_id!r} computes {int(local_dim)}; "
                f"rebuild the map with this model")

    def _open(self, path: Path) -> MapDatabase:
        return self._database(self._open_checked(path))

    def _open_checked(self, path: Path) -> KeyframeMap:
        """Open the map file ``path`` (format, model hash) and refuse one whose descriptor lengths the running
        model does not compute (``check_compatible``); closed again when refused."""
        kf_map = open_map(path, self.extractor.model_id, self.extractor.weights_sha256)
        try:
            self.check_compatible(kf_map.metadata, path)
        except BaseException:
            kf_map.close()
            raise
        return kf_map

    def _open_far_checked(self, path: Path) -> KeyframeMap:
        """Open the far-view companion ``path`` as ``_open_checked`` opens a map, under the far view's model
        (``far_extractor``: weights hash, descriptor lengths and the far view's image); closed again when refused.

        Raises:
            MapFormatError, ModelMismatchError: as ``_open_checked``; ConfigError: no far view is served here.
        """
        far = self.far_extractor
        if far is None:
            raise ConfigError("this service serves no far view (RERADAR_FAR_VIEW=false, or a model without one)")
        kf_map = open_map(path, far.model_id, far.weights_sha256)
        try:
            self.check_compatible(kf_map.metadata, path, far)
        except BaseException:
            kf_map.close()
            raise
        return kf_map

    def _database(self, kf_map: KeyframeMap, far_view: bool = True) -> MapDatabase:
        """The served database over the open, checked ``kf_map`` (index, keyframe cache, shared arrays) with its
        far-view companion when it has one and ``far_view`` (``_attach_far``); the map is closed when that fails."""
        try:
            db = MapDatabase(kf_map, self.index_config, keyframe_cache_size=self.settings.keyframe_cache_size,
                             config=self.settings.localization, preload=self.settings.preload_keyframes,
                             arrays_dir=self.settings.arrays_dir)
        except BaseException:
            kf_map.close()
            raise
        if far_view:
            self._attach_far(db)
        return db

    def _attach_far(self, db: MapDatabase) -> None:
        """Open the map's far-view companion (``far_view_path``) under the far view's model id and attach it. A
        companion that does not open or does not hold the map's keyframes is not served (logged); the map is."""
        path = far_view_path(db.map.path)
        if self.far_extractor is None or not (path.exists() or path.is_symlink()):
            return
        if not path.is_file():  # a folder, or a link to nothing, under the companion's name
            logger.warning("%s: far view not served: not a readable file", path.name)
            return
        try:  # read through in a child process first, as a map placed in the folder is (``_probe_unverified``)
            self._probe_unverified(_far_marker_id(path), path, file_identity(path))
            kf_map = self._open_far_checked(path)
            # the keyframes first: a companion of another map is refused before its shared arrays are written
            problem = far_view_mismatch(db.localizer.keyframes, kf_map,
                                        (db.metadata.radar_preset, kf_map.metadata.radar_preset))
            if problem is not None:
                kf_map.close()
                raise MapFormatError(f"it does not hold the keyframes of {db.map.path.name} ({problem}); rebuild "
                                     "it with `reradar build-map --far-view`")
            far = self._database(kf_map, far_view=False)
        except (ReRadarError, OSError) as exc:
            logger.warning("%s: far view not served: %s", path.name, exc)
            return
        try:
            db.attach_far(far)
        except ReRadarError as exc:
            far.close()
            logger.warning("%s: far view not served: %s", path.name, exc)
            return
        _log_far_served(path, db)

    def install_demo_map(self) -> None:
        """Copy the shipped demo map to ``<maps_dir>/demo.h5`` unless a map ``demo`` exists already; an
        installed demo map built with older weights is replaced when the shipped one fits the running model
        (a maps volume outlives image upgrades). Not after an operator deleted it (``DEMO_DELETED_MARKER``)."""
        target = self.path_for(DEMO_MAP_ID)
        if not target.exists() and (self.maps_dir / DEMO_DELETED_MARKER).exists():
            logger.info("demo map not installed: it was deleted (remove %s to get it back)", DEMO_DELETED_MARKER)
            return
        if not DEMO_MAP_PATH.is_file():
            logger.warning("demo map %s is not installed; run scripts/build_demo_map.py", DEMO_MAP_PATH)
            return
        if target.exists():
            try:
                installed, shipped = read_metadata(target), read_metadata(DEMO_MAP_PATH)
            except MapFormatError:
                return
            current = self.extractor.weights_sha256
            if not (installed.name == DEMO_MAP_ID and installed.weights_sha256 != current
                    and shipped.weights_sha256 == current):
                return
            logger.info("replacing the installed demo map (built with other weights) by the shipped one")
        tmp = self.staging_dir() / f"{uuid.uuid4().hex}.h5"
        shutil.copyfile(DEMO_MAP_PATH, tmp)
        install_file(tmp, target)

    def load_all(self) -> None:
        """Clean stale staging and temporary files, load every ``*.h5`` map in ``maps_dir``, and register the
        failed or interrupted builds from their job records."""
        shutil.rmtree(self.maps_dir / _STAGING, ignore_errors=True)
        remove_stale_temp_files(self.maps_dir)
        self._load_jobs()
        for path in sorted(self.maps_dir.glob("*.hdf5")):  # QA session 40: skipped without a word
            logger.warning("ignoring %s: the service serves <map_id>.h5 files; rename it to %s to serve it", path.name,
                           path.with_suffix(".h5").name)
        for path in sorted(self.maps_dir.glob("*.h5")):
            if path.name.endswith(FAR_VIEW_SUFFIX):  # a map's far-view companion, opened with its map
                owner = path.with_name(path.name[: -len(FAR_VIEW_SUFFIX)] + ".h5")
                if not owner.exists():  # not removed here: on a shared folder it may be another writer's, mid-install
                    logger.warning("%s: far-view companion without its map %s: not served. Most likely left by an "
                                   "install or a delete of map %s that was stopped midway: delete the file, or "
                                   "register map %s (which replaces or removes it). (A map file's name must not end "
                                   "in %s.)", path.name, owner.name, owner.stem, owner.stem, FAR_VIEW_SUFFIX)
                continue
            map_id = path.stem
            if not _ID_RE.fullmatch(map_id):
                logger.warning("ignoring %s: file name is not a valid map id", path)
                continue
            entry = self._load_entry(map_id, path)
            if entry.error is not None:
                logger.error("map %s not served: %s", map_id, entry.error)
            with self._lock:
                self._entries[map_id] = entry
        self.prune_map_arrays()

    def prune_map_arrays(self, dropped: MapDatabase | None = None) -> None:
        """Delete shared map arrays files (``maps.arrays``) no loaded map uses and unused for 10 minutes
        (files of replaced or deleted maps), and at once those of ``dropped`` (a map this registry no longer
        serves: deleted, forgotten or replaced) unless a loaded map uses the same file; processes still mapping one
        keep their pages, and one that opens it later rebuilds it."""
        arrays_dir = self.settings.arrays_dir
        if arrays_dir is None:
            return
        with self._lock:
            dbs = [d for e in self._entries.values() if e.db is not None for d in (e.db, e.db.far) if d is not None]
            keep = [d.arrays.path.name for d in dbs if d.arrays]
        gone = [d.arrays.path for d in (dropped, dropped.far if dropped is not None else None)
                if d is not None and d.arrays is not None and d.arrays.path.name not in keep]
        try:
            for path in gone:  # the age rule would keep a map's file for 10 minutes after a quick delete
                path.unlink(missing_ok=True)
            prune_arrays(arrays_dir, keep)
        except OSError as exc:
            logger.warning("could not prune map arrays in %s: %s", arrays_dir, exc)

    # ---- queries -------------------------------------------------------------------------------------------
    def build_note(self, entry: MapEntry) -> str | None:
        """Why a ``building`` entry may not be moving (``QueuedMapRegistry``: no live worker; here, where this
        process builds the map itself, only ``last_pass_note``)."""
        return last_pass_note(entry)

    def entries(self) -> list[MapEntry]:
        with self._lock:
            return sorted(self._entries.values(), key=lambda e: e.map_id)

    def get(self, map_id: str) -> MapEntry:
        self.validate_id(map_id)
        with self._lock:
            entry = self._entries.get(map_id)
        if entry is None:
            raise NotFoundError(f"unknown map {map_id!r}; GET /maps lists the registered maps")
        return entry

    def ready(self, map_id: str) -> MapDatabase:
        entry = self.get(map_id)
        if entry.state != "ready" or entry.db is None:
            detail = (f": {entry.error}" if entry.error else f" ({UPLOAD_CHECK_NOTE}; retry then)" if entry.uploaded
                      else f" ({entry.progress:.0%} built)")
            raise ConflictError(f"map {map_id!r} is not ready for queries, state {entry.state}{detail}")
        return entry.db

    @contextmanager
    def using(self, map_id: str) -> Iterator[MapDatabase]:
        """``ready(map_id)`` held for a request: a map deleted, dropped or replaced meanwhile stays open until
        the last request using it leaves this block, and is closed then (``_retire``). Access to the files of a
        map (keyframes read from the HDF5 file or the shared arrays) must happen inside it; its in-memory
        metadata and poses stay readable after it is closed."""
        with self._lock:  # one step with the lookup: a delete either comes first (404) or sees the holder
            db = self.ready(map_id)
            self._holders[db] = self._holders.get(db, 0) + 1
        try:
            yield db
        finally:
            self._let_go(db)

    def _let_go(self, db: MapDatabase) -> None:
        with self._lock:
            left = self._holders[db] - 1
            if left:
                self._holders[db] = left
                return
            del self._holders[db]
            if db not in self._retired:
                return
            self._retired.discard(db)
        db.close()

    def _retire(self, db: MapDatabase) -> None:
        """Close ``db``, which the registry no longer serves: at once when no request is using it (``using``),
        else when the last one finishes. Its files (HDF5 map, shared arrays mapping) are released then: a deleted
        map's disk space is freed and no file descriptor is left behind."""
        with self._lock:
            if self._holders.get(db):
                self._retired.add(db)
                return
        db.close()

    def _any_loaded(self, map_id: str | None, holds: Callable[[MapDatabase], bool]) -> bool:
        """``holds`` is true of map ``map_id``'s loaded database (None: of any loaded map's)."""
        with self._lock:
            entries = [self._entries.get(map_id)] if map_id else list(self._entries.values())
        return any(e is not None and e.db is not None and holds(e.db) for e in entries)

    def serves_far_view(self, map_id: str | None = None) -> bool:
        """Map ``map_id`` (None: any loaded map) has a far-view companion attached (``_attach_far``)."""
        return self._any_loaded(map_id, lambda db: db.far is not None)

    def serves_dense(self, map_id: str | None = None) -> bool:
        """Map ``map_id`` (None: any loaded map) has a far-view companion whose dense images this process correlates
        with (``MapDatabase.far_dense``)."""
        return self._any_loaded(map_id, lambda db: db.far_dense)

    @property
    def num_ready(self) -> int:
        with self._lock:
            return sum(e.state == "ready" for e in self._entries.values())

    # ---- mutation ------------------------------------------------------------------------------------------
    #: what a client may do about a map being built (``taken_message``): here a build cannot be cancelled
    _building_delete_hint = "then DELETE /maps/{map_id} to replace it"

    def taken_message(self, map_id: str, entry: MapEntry | None) -> str:
        """What to tell a client registering ``map_id`` when ``entry`` (None: a file without an entry) holds it:
        for a map being built, to wait for the build (and ``_building_delete_hint``)."""
        if entry is not None and entry.state == "building" and entry.uploaded:
            return (f"map {map_id!r} is taken: {UPLOAD_CHECK_NOTE}; pick another id, or DELETE /maps/{map_id} once "
                    "GET shows it ready to replace it")
        if entry is not None and entry.state == "building":
            hint = self._building_delete_hint.format(map_id=map_id)
            return (f"map {map_id!r} is being built ({entry.progress:.0%}); wait until the build finishes "
                    f"(GET /maps/{map_id} shows its state), {hint}, or pick another id")
        return f"map {map_id!r} already exists; DELETE /maps/{map_id} first or pick another id"

    def check_free(self, map_id: str) -> None:
        """Raise ``ConflictError`` (``taken_message``) when ``map_id`` is registered or its file exists."""
        with self._lock:
            path = self.path_for(map_id)
            if map_id not in self._entries and path.is_symlink() and not path.exists():
                raise ConflictError(f"a broken symbolic link {path.name} (its target is gone) lies in the maps folder "
                                    "under this id: an operator must remove or repoint it, or pick another id")
            if map_id in self._entries or map_name_taken(path):
                raise ConflictError(self.taken_message(map_id, self._entries.get(map_id)))

    def _reserve(self, map_id: str, scans_total: int = 0, far_view: bool = False, uploaded: bool = False) -> MapEntry:
        path = self.path_for(map_id)
        with self._lock:
            self.check_free(map_id)
            entry = MapEntry(map_id, path, "building", scans_total=scans_total, far_view=far_view, uploaded=uploaded)
            self._entries[map_id] = entry
            return entry

    def _release(self, map_id: str) -> None:
        with self._lock:
            self._entries.pop(map_id, None)

    def register_file(self, map_id: str, staged: Path, far_staged: Path | None = None) -> MapEntry:
        """Validate the uploaded map at ``staged`` (format, model hash, descriptor lengths and view) and install it
        as ``map_id``; with ``far_staged``, the uploaded far-view companion (``reradar build-map --far-view``'s
        ``<map>.far.h5``) too, checked likewise under the far view's model (``far_extractor``) and against the map's
        keyframes (count, poses, times: ``far_view_mismatch``), installed beside the map (``install_map_files``)
        and served with it.

        ``staged`` and ``far_staged`` must be inside the staging folder; they are moved (renamed) on success,
        deleted on failure. Each is read through in a child process first (``probe_map``), then opened once in
        this process: the checks before the install and the served database share that open file.

        The install never replaces a map file (``install_map_files``): on a shared maps folder another process
        may have installed a map under this id since the id check. The map is served with the uploaded companion
        only: a ``<map_id>.far.h5`` found in the folder without its map (left by an install or a delete stopped
        midway) is replaced, or removed when none is uploaded, and never served (``install_map_files``).

        Raises:
            ConflictError: the id is taken. BadRequestError: ``far_staged`` where no far view is served
            (``check_far_view_served``). MapFormatError / ModelMismatchError: invalid map or companion, or a
            companion that does not hold the map's keyframes (nothing stored, nothing registered).
        """
        staged_files = [staged] if far_staged is None else [staged, far_staged]
        try:
            if far_staged is not None:
                self.check_far_view_served("far_map_file")
            entry = self._reserve(map_id, uploaded=True)
        except BaseException:
            for path in staged_files:
                path.unlink(missing_ok=True)
            raise
        far_target = far_view_path(entry.path)
        installed = False
        kf_map: KeyframeMap | None = None
        far_kf: KeyframeMap | None = None
        db: MapDatabase | None = None
        far_db: MapDatabase | None = None
        try:
            try:
                # first in a child process: a crafted file that crashes or hangs the HDF5 library costs the child
                probe_map(staged)
                # then the one read in this process: checked before the file is installed (nothing of a map the
                # model cannot use is stored), and served from this same open file once installed
                kf_map = self._open_checked(staged)
            except ReRadarError as exc:  # the message names the staged file: say "the uploaded map" instead
                raise type(exc)(str(exc).replace(str(staged), "the uploaded map")) from None
            if far_staged is not None:
                try:
                    probe_map(far_staged)
                    far_kf = self._open_far_checked(far_staged)
                except ReRadarError as exc:
                    raise type(exc)(str(exc).replace(str(far_staged), "the uploaded far-view map ('far_map_file')")
                                    ) from None
                problem = far_view_mismatch(kf_map, far_kf, (kf_map.metadata.radar_preset, far_kf.metadata.radar_preset))
                if problem is not None:
                    raise MapFormatError(
                        f"the uploaded far-view map ('far_map_file') does not hold the keyframes of the uploaded map "
                        f"('map_file'): {problem}; send the <map>.far.h5 that `reradar build-map --far-view` wrote "
                        "together with this map (the same scans and poses), or register the map without it")
            identity = file_identity(staged)  # a hard link or a rename keeps it
            far_identity = file_identity(far_staged) if far_staged is not None else None
            try:
                install_map_files(staged, entry.path, far_staged)
            except FileExistsError:
                raise ConflictError(self.taken_message(map_id, None)) from None
            installed = True
            entry.file_id = identity
            # the open files are now the installed ones (same inodes, which a hard link or a rename keeps; HDF5
            # reads through its descriptor, never by name again): their messages name them by their new paths
            kf_map.path = entry.path
            try:  # opening reads every keyframe (shared arrays, preload): their checks refuse it here
                # with the uploaded companion only, never one found on disk (``install_map_files`` removed any)
                db = self._database(kf_map, far_view=False)  # closes ``kf_map`` when it fails
            except ReRadarError as exc:
                raise type(exc)(str(exc).replace(str(entry.path), "the uploaded map")) from None
            if far_kf is not None:
                far_kf.path = far_target
                opening, far_kf = far_kf, None  # ``_database`` closes it when it fails
                try:
                    far_db = self._database(opening, far_view=False)
                    db.attach_far(far_db)  # checked above (``far_view_mismatch``): the same keyframes
                except ReRadarError as exc:
                    raise type(exc)(str(exc).replace(str(far_target), "the uploaded far-view map")) from None
                far_db = None  # closed with ``db`` from now on
                _log_far_served(far_target, db)
            entry.db = db
            entry.scans_total = entry.scans_done = len(db)
            entry.state = "ready"
            self._mark_verified(map_id, identity)  # probed before the install: not again at the next start
            if far_identity is not None:
                self._mark_verified(_far_marker_id(far_target), far_identity)
            return entry
        except BaseException:
            for opened in (far_db, far_kf, db):  # closing twice is harmless (``_database`` may have)
                if opened is not None:
                    opened.close()
            if kf_map is not None and db is None:
                kf_map.close()
            for path in staged_files:
                path.unlink(missing_ok=True)
            if installed:  # only the files this call installed, never another writer's
                entry.path.unlink(missing_ok=True)
                if far_staged is not None:
                    far_target.unlink(missing_ok=True)
                fsync_dir(self.maps_dir)
            self._release(map_id)
            raise

    def start_build(self, map_id: str, scan_paths: list[Path], poses: np.ndarray, preset: str | None,
                    workdir: Path, source: str, far_view: bool = False,
                    pose_track: PoseSequence | None = None) -> MapEntry:
        """Reserve ``map_id`` and build its map from ``scan_paths`` in the background.

        ``poses`` (N, 3) float64 ``T_map_sensor`` per scan. ``workdir`` (extracted scans) is removed when the
        job ends; the map is written there and then installed (``install_map_files``). ``far_view``: also build
        the map's far-view companion from the same scans and poses (``build_map(far_view=...)``, as ``reradar
        build-map --far-view``; about as long again as the map's own pass), installed beside the map and served with
        it; a build without one removes a companion found without its map, as ``register_file`` does. Progress is
        visible through ``get(map_id)``: ``scans_total`` counts the scan descriptions, N or 2 N (``last_pass_note``
        says what a build standing still between them does).

        Raises:
            BadRequestError: ``far_view`` where no far view is served (``check_far_view_served``).
            ScanFormatError: the first scan is unreadable or its preset ambiguous. ConflictError: the id is taken.
        """
        if far_view:
            self.check_far_view_served("far_view")
        first = self._load_scan(scan_paths[0], preset)  # fail fast, synchronously, on unreadable scans
        if preset is None and range_bins_ambiguous(first.num_range_bins):
            # a PNG does not say its bin size: read as the first fitting preset, a boreas-2021 archive was built
            # 1.36x too long and answered 1.5 m off at confidence 1 (QA, session 24)
            raise ScanFormatError(
                f"the archive's scans have {first.num_range_bins} range bins, which fit radar presets of different "
                f"bin size ({preset_bin_sizes(presets_with_bins(first.num_range_bins))}): give 'preset', the one "
                "they were recorded with")
        preset_name = preset or first.preset or "unknown"
        entry = self._reserve(map_id, scans_total=len(scan_paths) * (2 if far_view else 1), far_view=far_view)
        try:
            self._write_job(entry, source)  # durable before the client is told 202
        except BaseException:
            self._release(map_id)
            raise

        def progress(done: int, total: int) -> None:
            entry.scans_done = done

        def job() -> None:
            # written in the job's folder and then installed with its far-view companion (the map is the commit
            # point, ``install_map_files``): the map appears whole
            built = workdir / f"{map_id}.h5"
            try:
                build_map(built, self.extractor, self.build_scan_loader(scan_paths, preset), poses,
                          radar_preset=preset_name, name=map_id, source=source,
                          batch_size=self.settings.build_batch_size, progress=progress,
                          localization=self.settings.localization,  # the place repetition under the serving settings
                          far_view=FarViewConfig() if far_view else None,
                          pose_at=None if pose_track is None else pose_file_reader(pose_track, preset))
                far_built = far_view_path(built) if far_view else None
                identity = file_identity(built)
                far_identity = file_identity(far_built) if far_built is not None else None
                try:
                    install_map_files(built, entry.path, far_built)
                except FileExistsError:
                    raise ConflictError(self.taken_message(map_id, None)) from None
                if far_identity is not None:  # written by this process: opened without a probe (``_attach_far``)
                    self._mark_verified(_far_marker_id(far_view_path(entry.path)), far_identity)
                # with the companion it built, never one found on disk (``install_map_files`` removed any)
                db = self._database(self._open_checked(entry.path), far_view=far_view)
                with self._lock:
                    entry.file_id = identity
                    entry.db = db
                    entry.scans_total = entry.scans_done = len(db)  # as a map loaded from its file
                    entry.state = "ready"
                self._drop_job(map_id)
                logger.info("map %s built: %d keyframes%s", map_id, len(db),
                            ", with its far view" if db.far is not None else "")
            except Exception as exc:  # noqa: BLE001 - a failed job is reported through GET /maps/{id}
                if isinstance(exc, ReRadarError | ServiceError):  # the upload's fault (a bad scan, pose file): no trace
                    logger.warning("building map %s failed: %s", map_id, scrub_paths(str(exc), [self.maps_dir]))
                else:
                    logger.exception("building map %s failed", map_id)
                entry.error = scrub_paths(build_failure_message(exc), [self.maps_dir])
                entry.state = "failed"
                try:
                    self._write_job(entry, source)
                except OSError:
                    logger.exception("could not record the failure of map %s", map_id)
            finally:
                shutil.rmtree(workdir, ignore_errors=True)

        self._executor.submit(job)
        return entry

    def _load_scan(self, path: Path, preset: str | None) -> RadarScan:
        """One archive scan, sized from its header before decoding (the same budget as uploaded scans). A polar
        .npy carries no time: its azimuths are timed from its file name ``<timestamp_us>.npy``."""
        try:
            limit, size = max_scan_file_bytes(self.settings.max_scan_pixels), path.stat().st_size
            if size > limit:  # never read a file no scan can fill (QA session 40)
                raise ScanFormatError(f"{size:,} bytes, more than a scan of at most "
                                      f"{self.settings.max_scan_pixels:,} pixels can be ({limit:,} bytes; "
                                      "RERADAR_MAX_SCAN_PIXELS)")
            data = path.read_bytes()
            header = scan_header(data)
            try:  # the uploads' rule
                check_header_size(header, self.settings.max_scan_pixels)
            except ScanTooLargeError as exc:  # a 422 of the build (the archive itself was within the body limit)
                raise ScanFormatError(f"{exc} (RERADAR_MAX_SCAN_PIXELS)") from None
            scan = load_scan_bytes(data, f"scan.{header.format}", preset)
        except ReRadarError as exc:
            raise type(exc)(f"{path.name}: {exc}") from exc
        match = SCAN_NAME_PATTERN.match(path.name)
        if header.format == "npy" and match is not None:  # else every keyframe would be at time 0
            scan = replace(scan, timestamps_us=scan.timestamps_us + int(match.group(1)))
        return scan

    def decoded_scan_time_us(self, path: Path, preset: str | None) -> int | None:
        """The time archive scan ``path`` carries as the build reads it (``_load_scan``: size-checked, then
        decoded); None when the build refuses the file (it then says why)."""
        try:
            return self._load_scan(path, preset).timestamp_us
        except ReRadarError:
            return None

    def scan_refusal(self, path: Path, preset: str | None) -> str | None:
        """Why the build refuses archive scan ``path`` (``_load_scan``'s message, naming the file), None when it
        reads it."""
        try:
            self._load_scan(path, preset)
        except ReRadarError as exc:
            return str(exc)
        return None

    def build_scan_loader(self, scan_paths: list[Path], preset: str | None) -> Callable[[int], RadarScan]:
        """``build_map``'s ``load_scan`` over an archive's scans (``_load_scan``), refusing at the first scan whose
        time (``RadarScan.timestamp_us``, by which the map keys its keyframes) an earlier scan had, or a PNG whose
        time lies more than one sweep from its file name's (at which its pose was taken): the upload's check
        (``archive.check_scan_times``) leaves to the build only PNGs the decoder refuses.

        Raises (from the loader): ScanFormatError naming both archive members and the time, or the member whose
        name and time disagree (``archive.scan_name_time_message``)."""
        seen: dict[int, str] = {}

        def load(i: int) -> RadarScan:
            path = scan_paths[i]
            scan = self._load_scan(path, preset)
            t = scan.timestamp_us
            if seen.setdefault(t, path.name) != path.name:
                raise ScanFormatError(duplicate_scan_time_message(seen[t], path.name, t))
            problem = scan_name_time_message(path.name, t, preset)
            if problem is not None:
                raise ScanFormatError(problem)
            return scan

        return load

    def delete(self, map_id: str) -> MapEntry:
        """Unregister ``map_id`` and delete its file (refused while it is being built)."""
        with self._lock:
            entry = self.get(map_id)
            refuse_delete_of_upload_in_check(entry)
            if entry.state == "building":
                raise ConflictError(f"map {map_id!r} is being built; wait for the job to finish")
            del self._entries[map_id]
            if map_id == DEMO_MAP_ID:  # before the file goes: a crash in between leaves neither to reinstall
                (self.maps_dir / DEMO_DELETED_MARKER).touch()
            # with the entry, under the lock: a folder pass (``adopt``) in between would load the file again
            entry.path.unlink(missing_ok=True)
        if entry.db is not None:  # requests already using it finish on the open file
            self._retire(entry.db)
        far_view_path(entry.path).unlink(missing_ok=True)
        self._verified_marker(map_id).unlink(missing_ok=True)
        self._verified_marker(_far_marker_id(far_view_path(entry.path))).unlink(missing_ok=True)
        self._drop_job(map_id)
        fsync_dir(self.maps_dir)
        self.prune_map_arrays(dropped=entry.db)
        return entry

    def close(self) -> None:
        """Stop the build jobs and close every loaded map (files, memory maps, keyframe caches)."""
        self._executor.shutdown(wait=True, cancel_futures=True)
        with self._lock:
            self._closed = True
            for entry in self._entries.values():
                if entry.db is not None:
                    entry.db.close()
            self._entries.clear()
            for db in self._retired:
                db.close()
            self._retired.clear()

    # ---- shared maps folder (several replicas; service.core.shared_state) ----------------------------------
    def adopt(self, map_id: str) -> MapEntry | None:
        """Load ``<maps_dir>/<map_id>.h5`` written by another process, unless this registry knows the id.

        Returns the new entry (``ready``, or ``failed`` with the reason), or None when nothing was done.
        """
        path = self.path_for(map_id)
        with self._lock:
            if map_id in self._entries or not path.is_file():
                return None
        entry = self._load_entry(map_id, path)
        with self._lock:
            if map_id in self._entries or self._closed:  # registered here meanwhile, or shut down
                if entry.db is not None:
                    entry.db.close()
                return None
            self._entries[map_id] = entry
        return entry

    def reopen_if_replaced(self, map_id: str) -> MapEntry | None:
        """Reopen ``map_id`` when the file under its name is not the one its entry opened (deleted and
        registered again by another process while this one missed it): the new map replaces the entry in one
        step and the old database is closed once no request is using it (``_retire``). A new file that fails to open makes the
        entry ``failed`` with the reason (as ``adopt``). Only entries opened from a file (``file_id``) qualify.

        Returns the new entry, or None when nothing changed (same file, file gone, or no such entry).
        """
        with self._lock:
            current = self._entries.get(map_id)
        if current is None or current.file_id is None or current.state == "building":
            return None
        identity = file_identity(current.path)
        if identity is None or identity == current.file_id:  # a file that is gone is ``forget``'s business
            return None
        entry = self._load_entry(map_id, current.path)
        with self._lock:
            if self._entries.get(map_id) is not current or self._closed:  # deleted or registered again meanwhile
                if entry.db is not None:
                    entry.db.close()
                return None
            self._entries[map_id] = entry
        if current.db is not None:  # requests already using the old map finish on it
            self._retire(current.db)
            self.prune_map_arrays(dropped=current.db)
        return entry

    def forget(self, map_id: str, expected: MapEntry | None = None) -> MapEntry | None:
        """Drop ``map_id`` from this registry without touching its file (another process deleted it); with
        ``expected``, only while that entry is still the one registered (a folder pass must not drop a build
        registered under the id since it looked).

        Its database is closed once no request is using it (``_retire``)."""
        with self._lock:
            if expected is not None and self._entries.get(map_id) is not expected:
                return None
            entry = self._entries.pop(map_id, None)
        if entry is not None and entry.db is not None:
            self._retire(entry.db)
            self.prune_map_arrays(dropped=entry.db)
        return entry
