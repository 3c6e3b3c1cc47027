"""Map builds on a job queue (``arq`` on the shared Redis), run by ``reradar worker`` processes.

With ``RERADAR_REDIS_URL`` set, ``POST /maps`` with a scan archive no longer builds inside the API process:

1. the API unpacks and checks the archive as before, moves it to ``<maps_dir>/.build-queue/<job_id>/`` (the maps
   folder is shared by every replica and worker), writes the job record ``build:<map_id>`` (a Redis hash:
   ``job_id, state, scans_done, scans_total, attempts, error, worker, heartbeat, cancel, installed, ...``) and
   enqueues an arq job; it answers 202;
2. a worker (``service.worker``) runs the build, updates ``scans_done`` after every batch and a heartbeat
   every 2 s, and on success leaves ``<maps_dir>/<map_id>.h5`` (written atomically, installed exclusively;
   ``installed`` records the file's identity first, ``installed_by``) and publishes a ``built`` event: every
   replica loads the map;
3. a worker killed mid-build leaves a record ``running`` whose heartbeat stops: after
   ``build_heartbeat_stale_s`` any live worker releases arq's in-progress lock on it and the build runs
   again (``attempts`` + 1, at most ``build_max_tries``); the record is durable as long as Redis persists
   (compose: append-only file);
4. ``DELETE /maps/<id>`` of a map still building cancels it: the record is flagged, the worker stops at
   its next batch, removes the job's files and the record. Flagging (``BuildQueue.cancel``) and the worker's
   ``ready`` transition (``BuildQueue.mark_ready``) are atomic on the record and exclude each other: a DELETE
   answered 200 as a cancel never leaves the map installed, and one that comes after ``ready`` deletes the map.

The record's key is also the fleet-wide claim of the id: ``HSETNX build:<id> job_id`` succeeds for one
request only. A prebuilt map file upload takes the same claim (``BuildQueue.claim_upload``: state
``uploading``, with a TTL in case its replica dies) until its file is installed and loaded (or the upload
failed), so an upload and a build, or two uploads, of one id on different replicas cannot both be accepted;
map files are installed exclusively (``install_file(exclusive=True)``) in case the claim could not be taken
(Redis down).

States of a record: ``queued``, ``running``, ``ready``, ``failed`` (with ``error``), ``cancelled``;
``uploading`` for an upload's claim (not in the ``builds`` set).
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import shutil
import socket
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, cast

import numpy as np
import redis

from maps.paths import far_view_path
from maps.store import fsync_dir
from reradar_core.io.poses import PoseSequence
from reradar_core.localization.extractor import FeatureExtractor
from service.core.config import Settings
from service.core.errors import ConflictError, NotFoundError
from service.core.registry import (
    UPLOAD_CHECK_NOTE,
    FileIdentity,
    MapEntry,
    MapRegistry,
    file_identity,
    last_pass_note,
    map_name_taken,
    refuse_delete_of_upload_in_check,
    utc_now,
)
from service.core.shared_state import SharedStateUnavailableError, arq_redis_settings

__all__ = ["BuildQueue", "QueuedMapRegistry", "JOB_FUNCTION", "ARQ_IN_PROGRESS_PREFIX", "ARQ_JOB_PREFIX", "jobs_dir",
           "orphan_job_age_s", "sweep_orphan_jobs", "identity_text", "installed_by", "remove_installed_map"]

logger = logging.getLogger(__name__)

#: Name of the arq function that builds a map (``service.worker``).
JOB_FUNCTION = "build_map"
#: A build job's copy of the uploaded pose file (timestamps_us, xy, yaw), which the worker's pose-clock check reads
#: (jobs queued before session 41 have none: their check reads the keyframe poses).
POSE_TRACK_FILE = "pose_track.npz"
#: arq's own key prefix for the lock a worker holds on a running job (``arq.constants``).
ARQ_IN_PROGRESS_PREFIX = "arq:in-progress:"
#: arq's key of a queued job's data (``arq.constants.job_key_prefix``)
ARQ_JOB_PREFIX = "arq:job:"

_ACTIVE = ("queued", "running")
#: record state of a prebuilt map file upload's claim on its id (``BuildQueue.claim_upload``)
UPLOADING = "uploading"
#: lifetime of an upload's claim, seconds, unless renewed: the registering request renews it every third of this
#: (``QueuedMapRegistry.register_file``) until the file is installed or refused, however long that takes; so the
#: TTL only frees the id of a replica that died meanwhile, within this time
UPLOAD_CLAIM_TTL_S = 30.0

# The record transitions below are Lua scripts: Redis runs each atomically (no other command in between).
#: KEYS[1] record; ARGV token, map id, created_utc, TTL ms -> 1 claimed, 0 taken
_CLAIM_UPLOAD = """
if redis.call('HSETNX', KEYS[1], 'job_id', ARGV[1]) == 0 then return 0 end
redis.call('HSET', KEYS[1], 'map_id', ARGV[2], 'state', 'uploading', 'created_utc', ARGV[3])
redis.call('PEXPIRE', KEYS[1], ARGV[4])
return 1
"""
#: KEYS[1] record; ARGV token -> 1 released, 0 not (or no longer) this upload's claim
_RELEASE_UPLOAD = """
if redis.call('HGET', KEYS[1], 'job_id') == ARGV[1] then return redis.call('DEL', KEYS[1]) end
return 0
"""
#: KEYS[1] record; ARGV token, TTL ms -> 1 renewed, 0 not (or no longer) this upload's claim
_RENEW_UPLOAD = """
if redis.call('HGET', KEYS[1], 'job_id') == ARGV[1] then return redis.call('PEXPIRE', KEYS[1], ARGV[2]) end
return 0
"""
#: KEYS[1] record, KEYS[2] builds set; ARGV job id, map id, scans done, scans total, error, finished_utc ->
#: 1 written, 0 a record exists
_RECORD_LOST = """
if redis.call('EXISTS', KEYS[1]) == 1 then return 0 end
redis.call('HSET', KEYS[1], 'job_id', ARGV[1], 'map_id', ARGV[2], 'state', 'failed', 'scans_done', ARGV[3],
           'scans_total', ARGV[4], 'attempts', 0, 'error', ARGV[5], 'worker', '', 'heartbeat', 0, 'cancel', 0,
           'source', '', 'created_utc', ARGV[6], 'finished_utc', ARGV[6])
redis.call('SADD', KEYS[2], ARGV[2])
return 1
"""
#: KEYS[1] record -> 1 flagged, 0 not active (finished, failed, gone): the worker's ``ready`` came first
_CANCEL_IF_ACTIVE = """
local state = redis.call('HGET', KEYS[1], 'state')
if state == 'queued' or state == 'running' then
  redis.call('HSET', KEYS[1], 'cancel', '1')
  return 1
end
return 0
"""
#: KEYS[1] record; ARGV job id, scans done, finished_utc -> 1 ready, 0 cancelled, -1 not this job's record
_MARK_READY = """
if redis.call('HGET', KEYS[1], 'job_id') ~= ARGV[1] then return -1 end
if redis.call('HGET', KEYS[1], 'cancel') == '1' then return 0 end
redis.call('HSET', KEYS[1], 'state', 'ready', 'scans_done', ARGV[2], 'finished_utc', ARGV[3])
return 1
"""


def build_note(rec: dict[str, str], newest_worker_beat: float | None, now: float, stale_after_s: float) -> str | None:
    """Why an active build (record ``rec``) may not be moving, for ``GET /maps``; None while a worker is on it.

    ``newest_worker_beat``: Unix time of the newest sign of life of any build worker (None: never one); a
    worker beats every few seconds (``service.worker``), so silence for ``stale_after_s`` means none runs."""
    if newest_worker_beat is None or now - newest_worker_beat > stale_after_s:
        return (f"no map-build worker has reported for over {stale_after_s:g} s: the build waits until one runs "
                "(start `reradar worker`; docs/OPERATIONS.md)")
    if rec.get("state") == "running" and now - float(rec.get("heartbeat") or 0.0) > stale_after_s:
        return "the worker building this map stopped reporting; a live worker will retry the build"
    return None


def jobs_dir(maps_dir: Path) -> Path:
    """Where queued builds keep their scans and write their map before installing it: inside the shared maps
    folder (same file system: the install is a rename), apart from the single-process build records in
    ``.jobs`` and from the temporary files replicas clean up at start-up."""
    return maps_dir / ".build-queue"


def identity_text(identity: FileIdentity | None) -> str:
    """A ``FileIdentity`` as a record field (``installed``)."""
    return ",".join(map(str, identity)) if identity is not None else ""


def installed_by(rec: dict[str, str], target: Path) -> bool:
    """Whether ``target`` is the map file an attempt of the build of ``rec`` installed: its ``installed`` field,
    written by the worker before the install (a hard link keeps the file's identity). Such a file is the
    build's own on a retry, and goes when the build is cancelled."""
    return bool(rec.get("installed")) and rec.get("installed") == identity_text(file_identity(target))


def remove_installed_map(rec: dict[str, str], target: Path) -> bool:
    """Remove ``target`` when it is the map file an attempt of the build of ``rec`` installed (``installed_by``:
    never a map registered otherwise), and its far-view companion (installed with it by the same attempt),
    durably; whether it did."""
    if not installed_by(rec, target):
        return False
    target.unlink(missing_ok=True)
    far_view_path(target).unlink(missing_ok=True)
    fsync_dir(target.parent)
    return True


def orphan_job_age_s(settings: Settings) -> float:
    """How long a job folder without a build record is left alone (``sweep_orphan_jobs``): far longer than an
    API replica takes between creating it and writing the record, and than a running build goes without
    writing into it."""
    return max(300.0, 4 * settings.build_heartbeat_stale_s)


def sweep_orphan_jobs(queue: BuildQueue, maps_dir: Path, min_age_s: float, now: float | None = None) -> list[str]:
    """Remove ``<maps_dir>/.build-queue/<job_id>/`` folders whose job has no build record (Redis restarted
    without its data, or a replica died between staging a job and writing its record) and in which nothing
    changed for ``min_age_s``. A folder being staged by an API replica (written before its record) or written
    by a build is younger than that. Returns the job ids removed.

    Raises:
        redis.RedisError: the records cannot be read (nothing is removed then).
    """
    root = jobs_dir(maps_dir)
    if not root.is_dir():
        return []
    now = time.time() if now is None else now
    owned = {rec.get("job_id") for rec in queue.records().values()}
    removed = []
    for job in root.iterdir():
        if job.name in owned or not job.is_dir():
            continue
        try:  # the folder and what is directly in it (spec, poses, the map a build writes)
            newest = max([job.stat().st_mtime, *(p.stat().st_mtime for p in job.iterdir())])
        except OSError:  # removed meanwhile
            continue
        if now - newest < min_age_s:
            continue
        shutil.rmtree(job, ignore_errors=True)
        removed.append(job.name)
    if removed:
        logger.warning("removed %d build job folder(s) without a build record (Redis lost its data?): %s",
                       len(removed), ", ".join(sorted(removed)))
    return removed


class BuildQueue:
    """Job records (Redis hashes) and the arq queue of map builds."""

    def __init__(self, client: redis.Redis, keys: Any, settings: Settings) -> None:
        self.redis = client
        self.keys = keys
        self.settings = settings

    # ---- records --------------------------------------------------------------------------------------
    def record(self, map_id: str) -> dict[str, str]:
        raw = cast(dict[bytes, bytes], self.redis.hgetall(self.keys.build(map_id)))
        return {k.decode(): v.decode() for k, v in raw.items()}

    def records(self) -> dict[str, dict[str, str]]:
        ids = sorted(m.decode() for m in cast(set[bytes], self.redis.smembers(self.keys.builds)))
        pipe = self.redis.pipeline(transaction=False)
        for map_id in ids:
            pipe.hgetall(self.keys.build(map_id))
        out = {}
        # a key of another type under the namespace (a foreign writer) is skipped, not an outage of every pass
        for map_id, raw in zip(ids, pipe.execute(raise_on_error=False), strict=True):
            if isinstance(raw, dict) and raw:
                out[map_id] = {k.decode(): v.decode() for k, v in raw.items()}
            elif isinstance(raw, Exception):
                logger.warning("build record of %s is unreadable (%s); skipped", map_id, raw)
        return out

    def update(self, map_id: str, /, **fields: object) -> None:
        self.redis.hset(self.keys.build(map_id), mapping={k: str(v) for k, v in fields.items()})

    def newest_worker_beat(self) -> float | None:
        """Unix time of the newest sign of life of any build worker (``Keys.worker_heartbeats``); None if none."""
        beats = []
        for raw in cast(list[bytes], self.redis.hvals(self.keys.worker_heartbeats)):
            try:
                beats.append(float(raw))
            except ValueError:  # a foreign value under the namespace
                continue
        return max(beats, default=None)

    def remove(self, map_id: str) -> None:
        # no MULTI: Redis refuses a transaction over its memory limit, and the rollback of a refused enqueue
        # must still free the id (plain DEL / SREM are allowed then)
        pipe = self.redis.pipeline(transaction=False)
        pipe.delete(self.keys.build(map_id))
        pipe.srem(self.keys.builds, map_id)
        pipe.execute()

    def record_lost(self, map_id: str, job_id: str, scans_done: int, scans_total: int, error: str) -> bool:
        """Write a ``failed`` record for the build ``job_id`` of ``map_id`` whose record Redis lost, unless a
        record of the id exists (another replica wrote it first, or the id was claimed again). Its job id is
        ``lost-<job_id>``, so a worker still running the job cannot mark it ``ready`` (``mark_ready``: not this
        job's record) and the job's folder counts as an orphan (``sweep_orphan_jobs``). Returns whether it
        was written."""
        return bool(self.redis.eval(_RECORD_LOST, 2, self.keys.build(map_id), self.keys.builds, f"lost-{job_id}",
                                    map_id, str(scans_done), str(scans_total), error, utc_now()))

    # ---- the fleet-wide claim of an id --------------------------------------------------------------------
    def taken_error(self, map_id: str) -> ConflictError:
        """The 409 for a request that found ``map_id`` claimed by the record of another build or upload."""
        rec = self.record(map_id)
        state = rec.get("state")
        if rec.get("cancel") == "1":
            return ConflictError(f"map {map_id!r}: its cancelled build is stopping (at its next batch); retry in a "
                                 "few seconds")
        if state == UPLOADING:
            return ConflictError(f"map {map_id!r} is being registered right now by another request (a map file "
                                 f"upload); once it is done the id is taken: GET /maps/{map_id} shows it, "
                                 f"DELETE /maps/{map_id} frees it; or pick another id")
        if state in _ACTIVE:
            return ConflictError(f"map {map_id!r} is already being built; wait until the build finishes "
                                 f"(GET /maps/{map_id} shows its state), DELETE /maps/{map_id} to cancel it, or "
                                 "pick another id")
        if state == "failed":
            return ConflictError(f"map {map_id!r}: its build failed; DELETE /maps/{map_id} first or pick another "
                                 "id")
        if state == "ready":
            return ConflictError(f"map {map_id!r} already exists; DELETE /maps/{map_id} first or pick another id")
        # the claim went away between the two calls
        return ConflictError(f"map {map_id!r} was claimed by another request moments ago; retry in a second or "
                             "pick another id")

    def claim_upload(self, map_id: str, token: str, ttl_s: float | None = None) -> None:
        """Claim ``map_id`` for a prebuilt map file upload: the build record's claim (``enqueue``), as a record
        in state ``uploading`` that expires after ``ttl_s`` (default ``UPLOAD_CLAIM_TTL_S``) unless renewed
        (``renew_upload``). Release it with ``release_upload``.

        Raises:
            ConflictError: a build or another upload holds the id. redis.RedisError: Redis is down.
        """
        ttl_ms = int((UPLOAD_CLAIM_TTL_S if ttl_s is None else ttl_s) * 1000)
        claimed = self.redis.eval(_CLAIM_UPLOAD, 1, self.keys.build(map_id), token, map_id, utc_now(), str(ttl_ms))
        if not claimed:
            raise self.taken_error(map_id)

    def renew_upload(self, map_id: str, token: str, ttl_s: float | None = None) -> bool:
        """Extend the claim of ``claim_upload(map_id, token)`` to ``ttl_s`` (default ``UPLOAD_CLAIM_TTL_S``) from
        now; False when it is no longer this upload's (it expired, Redis lost it)."""
        ttl_ms = int((UPLOAD_CLAIM_TTL_S if ttl_s is None else ttl_s) * 1000)
        return bool(self.redis.eval(_RENEW_UPLOAD, 1, self.keys.build(map_id), token, str(ttl_ms)))

    def release_upload(self, map_id: str, token: str) -> None:
        """Free ``map_id`` claimed by ``claim_upload(map_id, token)``; a claim of another request (this one
        expired meanwhile) is left alone."""
        self.redis.eval(_RELEASE_UPLOAD, 1, self.keys.build(map_id), token)

    def mark_ready(self, map_id: str, job_id: str, scans_done: int) -> int:
        """The worker's final transition of a build whose map it installed: ``ready``, unless a DELETE flagged
        the record (``cancel``), atomically (``cancel`` flags only an active record). Returns 1 (``ready``), 0
        (cancelled: the map must go) or -1 (the record is not ``job_id``'s: Redis lost it)."""
        return int(cast(int, self.redis.eval(_MARK_READY, 1, self.keys.build(map_id), job_id, str(scans_done),
                                              utc_now())))

    # ---- enqueue / cancel ---------------------------------------------------------------------------------
    def enqueue(self, map_id: str, job_id: str, scans_total: int, source: str,
                taken: Callable[[], bool] | None = None, far_view: bool = False) -> None:
        """Claim ``map_id`` across every replica, write its record and put the build on the queue.

        ``taken``: checked once the claim is held (a map file installed under the id since the caller's
        check, whose upload claimed and released the id before this claim, frees the claim again: 409).
        ``far_view``: the build also builds the map's far-view companion (the record's ``far_view``, 1 or 0, which
        every replica shows while it is building).

        Raises:
            ConflictError: another build or upload of ``map_id`` exists. redis.RedisError: Redis is down.
        """
        key = self.keys.build(map_id)
        if not self.redis.hsetnx(key, "job_id", job_id):
            raise self.taken_error(map_id)
        try:  # from the claim on, a failure frees the id again ("nothing was stored")
            if taken is not None and taken():
                raise ConflictError(f"map {map_id!r} already exists (registered by another request moments "
                                    f"ago); DELETE /maps/{map_id} first or pick another id")
            self.update(map_id, map_id=map_id, state="queued", scans_done=0, scans_total=scans_total, attempts=0,
                        error="", worker="", heartbeat=0, cancel=0, source=source, created_utc=utc_now(),
                        far_view=int(far_view))
            self.redis.sadd(self.keys.builds, map_id)
            asyncio.run(self._enqueue(map_id, job_id))
        except BaseException:
            self.remove(map_id)
            raise

    async def _enqueue(self, map_id: str, job_id: str) -> None:
        from arq import create_pool

        pool = await create_pool(arq_redis_settings(self.settings.redis_url or ""),
                                 default_queue_name=self.keys.queue)
        try:
            await pool.enqueue_job(JOB_FUNCTION, map_id, job_id, _job_id=job_id)
        finally:
            await pool.aclose()

    def cancel(self, map_id: str, remove_files: Callable[[dict[str, str]], None] | None = None
               ) -> tuple[bool, str | None]:
        """Stop building ``map_id``. A build no worker has started is taken off the queue at once (its id is free
        again); a running one is flagged and stops at its next batch.

        The flag is set only while the record is still active, atomically (``_CANCEL_IF_ACTIVE``): a build
        that its worker marked ``ready`` first is not cancelled (False: delete the map instead).

        ``remove_files(record)`` removes the files of a build taken off the queue (no worker will; among them a
        map an earlier attempt installed, ``installed_by``), before its record goes: a replica that finds the
        record gone and the files still there takes it for lost data.

        Returns:
            (whether a queued or running build was cancelled, the job id when it was taken off the queue).
        """
        rec = self.record(map_id)
        if rec.get("state") not in _ACTIVE:
            return False, None
        job_id = rec.get("job_id", "")
        if rec.get("state") == "queued" and job_id and not self.redis.exists(ARQ_IN_PROGRESS_PREFIX + job_id):
            pipe = self.redis.pipeline(transaction=False)
            pipe.zrem(self.keys.queue, job_id)
            pipe.delete(ARQ_JOB_PREFIX + job_id)  # a worker that dequeues it meanwhile finds no job and skips it
            removed = pipe.execute()
            if removed[0]:
                if remove_files is not None:
                    remove_files(rec)
                self.remove(map_id)
                return True, job_id
        flagged = self.redis.eval(_CANCEL_IF_ACTIVE, 1, self.keys.build(map_id))
        return bool(flagged), None


class QueuedMapRegistry(MapRegistry):
    """A ``MapRegistry`` whose archive builds go to the job queue and whose view of builds comes from the
    job records (so every replica shows a map being built, with its progress)."""

    def __init__(self, settings: Settings, extractor: FeatureExtractor, queue: BuildQueue,
                 publish: Callable[[str, str], None]) -> None:
        super().__init__(settings, extractor)
        self.queue = queue
        self._publish = publish
        #: job id of each build this replica shows ``building`` (to tell a lost record from a cancelled build)
        self._job_ids: dict[str, str] = {}
        #: ids this replica is registering right now (reserved here, record or file not yet written): the map
        #: sync must not take their ``building`` entry for a vanished build
        self._registering: Counter[str] = Counter()

    @contextmanager
    def _in_flight(self, map_id: str) -> Iterator[None]:
        with self._lock:
            self._registering[map_id] += 1
        try:
            yield
        finally:
            with self._lock:
                self._registering[map_id] -= 1
                if self._registering[map_id] <= 0:
                    del self._registering[map_id]

    def staging_dir(self) -> Path:
        """A staging folder of this process only: the base ``load_all`` empties ``.staging`` at start-up,
        which on a shared maps folder would break another replica's upload in flight."""
        d = self.maps_dir / f".staging-{socket.gethostname()}-{os.getpid()}"
        d.mkdir(exist_ok=True)
        return d

    #: here ``DELETE`` cancels a build (``MapRegistry.taken_message``)
    _building_delete_hint = "or DELETE /maps/{map_id} to cancel the build"

    def load_all(self) -> None:
        """As ``MapRegistry.load_all``, and remove staging folders of replicas gone for over an hour."""
        super().load_all()
        cutoff = time.time() - 3600
        for d in self.maps_dir.glob(".staging-*"):
            try:
                if d.is_dir() and d.stat().st_mtime < cutoff:
                    shutil.rmtree(d, ignore_errors=True)
            except OSError:
                continue

    def check_free(self, map_id: str) -> None:
        """As ``MapRegistry.check_free``, deciding from the shared maps folder rather than this replica's view: a
        map whose file is gone (deleted through another replica moments ago, before this one's map sync
        dropped it) no longer holds the id."""
        with self._lock:
            entry = self._entries.get(map_id)
            if (entry is not None and entry.file_id is not None and entry.state != "building"
                    and not entry.path.exists()):
                self.forget(map_id)
                logger.info("map %s dropped: deleted by another replica", map_id, extra={"map_id": map_id})
            super().check_free(map_id)

    def register_file(self, map_id: str, staged: Path, far_staged: Path | None = None) -> MapEntry:
        """As ``MapRegistry.register_file``, holding the fleet-wide claim of ``map_id``
        (``BuildQueue.claim_upload``) from before the id check until the upload is installed or failed: a build
        or another upload of the id through any replica meanwhile gets 409. Redis down: the upload goes ahead
        unclaimed (a map file upload needs no queue); its install still never replaces a file.

        Raises:
            ConflictError: the id is taken or claimed. MapFormatError / ModelMismatchError: invalid map.
        """
        token = f"upload-{uuid.uuid4().hex}"
        claimed = False
        try:
            self.path_for(map_id)
            self.queue.claim_upload(map_id, token)
            claimed = True
        except redis.RedisError as exc:
            logger.warning("map %s: upload not claimed in Redis (%s); installed only if the id is free", map_id, exc)
        except BaseException:
            staged.unlink(missing_ok=True)
            if far_staged is not None:
                far_staged.unlink(missing_ok=True)
            raise
        try:
            with self._in_flight(map_id), self._claim_kept(map_id, token, claimed):
                return super().register_file(map_id, staged, far_staged)
        finally:
            if claimed:
                try:
                    self.queue.release_upload(map_id, token)
                except redis.RedisError as exc:
                    logger.warning("map %s: upload claim not released (Redis: %s); it expires within %.0f s", map_id,
                                   exc, UPLOAD_CLAIM_TTL_S)

    @contextmanager
    def _claim_kept(self, map_id: str, token: str, claimed: bool) -> Iterator[None]:
        """Renew the upload's claim (``renew_upload``) every third of ``UPLOAD_CLAIM_TTL_S`` while the body runs:
        checking and installing a large map may take longer than the TTL, which is kept short so that the claim
        of a replica that died mid-upload frees the id soon."""
        if not claimed:
            yield
            return
        stop = threading.Event()

        def renew() -> None:
            while not stop.wait(UPLOAD_CLAIM_TTL_S / 3):
                try:
                    if not self.queue.renew_upload(map_id, token):
                        logger.warning("map %s: upload claim lost (expired or Redis lost it); the install still "
                                       "never replaces a file", map_id)
                        return
                except redis.RedisError as exc:  # a short outage: the claim lives on until its TTL
                    logger.warning("map %s: upload claim not renewed (Redis: %s)", map_id, exc)

        thread = threading.Thread(target=renew, name=f"upload-claim-{map_id}", daemon=True)
        thread.start()
        try:
            yield
        finally:
            stop.set()
            thread.join()

    def build_note(self, entry: MapEntry) -> str | None:
        """``build_note`` of a ``building`` entry from its job record and the workers' heartbeats (None when
        Redis cannot say: the note is a hint, the state stays what the records last said)."""
        if entry.state != "building":
            return None
        if entry.uploaded:
            return UPLOAD_CHECK_NOTE
        try:
            rec = self.queue.record(entry.map_id)
            if rec.get("state") not in _ACTIVE:
                return None
            return build_note(rec, self.queue.newest_worker_beat(), time.time(),
                              self.settings.build_heartbeat_stale_s) or last_pass_note(entry)
        except redis.RedisError:
            return None

    def start_build(self, map_id: str, scan_paths: list[Path], poses: np.ndarray, preset: str | None,
                    workdir: Path, source: str, far_view: bool = False,
                    pose_track: PoseSequence | None = None) -> MapEntry:
        """Reserve ``map_id``, move ``workdir`` to the shared jobs folder and enqueue its build (``far_view``:
        with its far-view companion, built by the worker as ``MapRegistry.start_build`` builds it)."""
        if far_view:
            self.check_far_view_served("far_view")
        with self._in_flight(map_id):
            return self._queue_build(map_id, scan_paths, poses, preset, workdir, source, far_view, pose_track)

    def _queue_build(self, map_id: str, scan_paths: list[Path], poses: np.ndarray, preset: str | None,
                     workdir: Path, source: str, far_view: bool = False,
                     pose_track: PoseSequence | None = None) -> MapEntry:
        first = self._load_scan(scan_paths[0], preset)  # fail fast, synchronously, on unreadable scans
        preset_name = preset or first.preset or "unknown"
        scans_total = len(scan_paths) * (2 if far_view else 1)  # scan descriptions: the far view's follow
        entry = self._reserve(map_id, scans_total=scans_total, far_view=far_view)
        job_id = uuid.uuid4().hex
        job_dir = jobs_dir(self.maps_dir) / job_id
        try:
            job_dir.mkdir(parents=True)
            os.replace(workdir, job_dir / "work")
            np.save(job_dir / "poses.npy", np.asarray(poses, dtype=np.float64))
            if pose_track is not None:  # the worker's pose-clock check reads the pose file itself (pose_file_reader)
                np.savez(job_dir / POSE_TRACK_FILE, timestamps_us=pose_track.timestamps_us, xy=pose_track.xy,
                         yaw=pose_track.yaw)
            spec = {"map_id": map_id, "job_id": job_id, "preset": preset, "preset_name": preset_name,
                    "source": source, "scans": [str(p.relative_to(workdir)) for p in scan_paths],
                    "far_view": far_view}
            (job_dir / "spec.json").write_text(json.dumps(spec))
            try:
                self.queue.enqueue(map_id, job_id, scans_total, source, taken=lambda: map_name_taken(self.path_for(map_id)),
                                   far_view=far_view)
            except redis.RedisError as exc:
                full = isinstance(exc, redis.exceptions.OutOfMemoryError) or "OOM" in str(exc)
                logger.warning("map %s: build not queued (Redis %s)", map_id, "full" if full else "unavailable")
                raise SharedStateUnavailableError(
                    ("map builds are queued in Redis, which is full (its maxmemory is reached: the operator must "
                     "raise RERADAR_REDIS_MAXMEMORY or free keys)" if full else
                     "map builds are queued in Redis, which is unavailable") +
                    "; nothing was stored, retry later (or upload a prebuilt map file, which needs no queue)"
                ) from exc
        except BaseException:
            shutil.rmtree(job_dir, ignore_errors=True)
            self._release(map_id)
            raise
        with self._lock:
            self._job_ids[map_id] = job_id
        logger.info("map %s: build queued as job %s (%d scans)", map_id, job_id, len(scan_paths),
                    extra={"map_id": map_id, "job_id": job_id})
        self._publish("queued", map_id)
        return entry

    def _remove_job_files(self, rec: dict[str, str]) -> None:
        """The files of a build taken off the queue: its job folder, and the map an earlier attempt installed
        before it stopped short of ``ready`` (the DELETE that took it off was answered 200)."""
        map_id = rec.get("map_id", "")
        if map_id:
            remove_installed_map(rec, self.path_for(map_id))
        if rec.get("job_id"):
            shutil.rmtree(jobs_dir(self.maps_dir) / rec["job_id"], ignore_errors=True)

    def delete(self, map_id: str) -> MapEntry:
        """Delete a map; a map still building is cancelled (its job stops at the next batch and never leaves
        the map installed: ``BuildQueue.cancel``). A build that finished or failed since this replica last
        looked is deleted like any map (``_settle_finished_build``); a build of the id still active after the
        map was deleted is cancelled too, so it cannot bring the map back."""
        entry = self.get(map_id)
        refuse_delete_of_upload_in_check(entry)  # before the queue is asked: an upload has no job to cancel
        if entry.state == "building":
            try:
                cancelled, _dropped = self.queue.cancel(map_id, self._remove_job_files)
                rec = {} if cancelled else self.queue.record(map_id)
            except redis.RedisError as exc:
                raise SharedStateUnavailableError(
                    f"map {map_id!r} is being built and build jobs live in Redis, which is unavailable; retry "
                    f"later") from exc
            if cancelled:
                with self._lock:
                    self._entries.pop(map_id, None)
                    self._job_ids.pop(map_id, None)
                logger.info("map %s: build cancelled", map_id, extra={"map_id": map_id})
                self._publish("cancelled", map_id)
                return entry
            self._settle_finished_build(map_id, entry, rec)
        entry = super().delete(map_id)  # the "deleted" event is published by OpsMiddleware
        try:
            rec = self.queue.record(map_id)
            if rec.get("state") in _ACTIVE:  # its worker installed the map, not yet ``ready``: it removes it again
                self.queue.cancel(map_id, self._remove_job_files)
            elif rec.get("state") != UPLOADING:  # another request's upload claim is its own to release
                self.queue.remove(map_id)  # a finished or failed build's record goes with the map
        except redis.RedisError:
            logger.warning("map %s deleted, but its build record could not be removed (Redis down)", map_id)
        return entry

    def _settle_finished_build(self, map_id: str, entry: MapEntry, rec: dict[str, str]) -> None:
        """Replace ``entry`` (``building`` here, but its build record ``rec`` is no longer active: the build
        finished or failed since this replica last looked) by what the shared state holds, without loading
        the map, so that ``MapRegistry.delete`` deletes it: the installed map file, or the failed build.

        Raises:
            NotFoundError: neither a map file nor a record is left (the build was cancelled elsewhere).
        """
        path = self.path_for(map_id)
        on_disk = path.is_file()
        if not on_disk and rec.get("state") in (None, UPLOADING):  # an upload's claim is not this build's
            with self._lock:
                if self._entries.get(map_id) is entry:
                    del self._entries[map_id]
            raise NotFoundError(f"unknown map {map_id!r}: its build was cancelled or removed meanwhile; GET /maps "
                                "lists the registered maps")
        settled = MapEntry(map_id, path, "ready" if on_disk else "failed", error=None if on_disk else (
                           rec.get("error") or "failed"), scans_done=int(rec.get("scans_done") or 0),
                           scans_total=int(rec.get("scans_total") or 0), registered_utc=entry.registered_utc,
                           file_id=file_identity(path))
        with self._lock:
            if self._entries.get(map_id) is entry:
                self._entries[map_id] = settled
                self._job_ids.pop(map_id, None)

    def _swap_in_built(self, map_id: str) -> None:
        """Replace the ``building`` entry of a finished build by the loaded map, in one step (a request
        never sees the id missing in between)."""
        entry = self._load_entry(map_id, self.path_for(map_id))
        with self._lock:
            current = self._entries.get(map_id)
            # a failed build never had a file: one under its id now is a map registered since
            if current is None or current.state == "building" or (current.state == "failed"
                                                                   and current.file_id is None):
                self._entries[map_id] = entry
                self._job_ids.pop(map_id, None)
                return
        if entry.db is not None:  # someone else loaded it meanwhile
            entry.db.close()

    def reconcile_builds(self) -> None:
        """Mirror the job records into this registry: active builds as ``building`` with their progress,
        failed ones as ``failed`` with the reason (unless a map file holds the id: a map registered while the
        build ran, which made it fail, is served); finished ones are loaded by ``MapSync``'s file pass. A
        building map whose record vanished while its job's files are still there (Redis restarted without its
        data) is dropped with a warning."""
        records = self.queue.records()
        for map_id, rec in records.items():
            state = rec.get("state")
            cancelled = rec.get("cancel") == "1"
            with self._lock:
                entry = self._entries.get(map_id)
            if state in _ACTIVE and not cancelled:
                if entry is None:
                    entry = MapEntry(map_id, self.path_for(map_id), "building")
                    with self._lock:
                        entry = self._entries.setdefault(map_id, entry)
                if entry.state == "building":
                    entry.scans_done = int(rec.get("scans_done", 0))
                    entry.scans_total = int(rec.get("scans_total", 0))
                    entry.far_view = rec.get("far_view") == "1"
                    if rec.get("job_id"):
                        with self._lock:
                            self._job_ids[map_id] = rec["job_id"]
            elif state == "failed" and (entry is None or entry.state == "building" or (
                    entry.state == "failed" and entry.file_id is None)):
                if self.path_for(map_id).is_file():
                    self._swap_in_built(map_id)
                elif entry is None or entry.state == "building":
                    failed = MapEntry(map_id, self.path_for(map_id), "failed", error=rec.get("error") or "failed",
                                      scans_done=int(rec.get("scans_done", 0)),
                                      scans_total=int(rec.get("scans_total", 0)))
                    with self._lock:
                        self._entries[map_id] = failed
                        self._job_ids.pop(map_id, None)
            elif state == "ready" and entry is not None and entry.state == "building":
                self._swap_in_built(map_id)
        # builds that vanished (cancelled and cleaned up) leave no building entry behind
        with self._lock:
            stale = [m for m, e in self._entries.items() if e.db is None and m not in self._registering and (
                (e.state == "building" and (m not in records or records[m].get("cancel") == "1"))
                # a failed build deleted through another replica: its record is gone and it never had a file
                or (e.state == "failed" and m not in records and not e.path.exists()))]
            lost = []
            for m in stale:
                gone = self._entries.pop(m)
                job_id = self._job_ids.pop(m, None)
                # a cancelled build's files go before its record; a lost record leaves them behind
                if (gone.state == "building" and m not in records and job_id
                        and (jobs_dir(self.maps_dir) / job_id).is_dir()):
                    lost.append((gone, job_id))
        for gone, job_id in lost:
            self._record_lost_build(gone, job_id)

    def _record_lost_build(self, gone: MapEntry, job_id: str) -> None:
        """A build this replica showed ``building`` whose record vanished while its job's files are still there
        (Redis restarted without its data): say ``failed`` with the reason, on every replica (a failed record
        written once, ``BuildQueue.record_lost``), rather than let the map vanish (404). The job's files are
        left to ``sweep_orphan_jobs``; a worker still running the job keeps the map it installs (a map file wins
        over a failed record)."""
        map_id = gone.map_id
        error = (f"the build was lost: the shared state (Redis) lost its record while it was "
                 f"{'queued' if gone.scans_done == 0 else 'running'} (restarted without its data?); "
                 f"DELETE /maps/{map_id} and register the map again")
        logger.warning("map %s: its build record vanished from Redis while it was being built (Redis restarted "
                       "without its data?); the build is lost and shown as failed: register the map again", map_id,
                       extra={"map_id": map_id, "job_id": job_id})
        try:
            if not self.queue.record_lost(map_id, job_id, gone.scans_done, gone.scans_total, error):
                return  # another replica said so first, or the id was registered again meanwhile: the next pass
        except redis.RedisError as exc:
            logger.warning("map %s: the lost build could not be recorded (Redis: %s)", map_id, exc)
            return
        with self._lock:
            self._entries.setdefault(map_id, MapEntry(map_id, self.path_for(map_id), "failed", error=error,
                                                      scans_done=gone.scans_done, scans_total=gone.scans_total))
