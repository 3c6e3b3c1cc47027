"""Map builds on a job queue (``arq`` on the shared Redis), run by ``reradar worker`` processes.

With ``RERADAR_REDIS_URL`` set, ``POST /maps`` with a scan archive no longer builds inside the API process:

1. the API unpacks and checks the archive as before, moves it to ``<maps_dir>/.build-queue/<job_id>/`` (the maps
   folder is shared by every replica and worker), writes the job record ``build:<map_id>`` (a Redis hash:
   ``job_id, state, scans_done, scans_total, attempts, error, worker, heartbeat, cancel, ...``) and enqueues
   an arq job; it answers 202;
2. a worker (``service.worker``) runs the build, updates ``scans_done`` after every batch and a heartbeat
   every 2 s, and on success leaves ``<maps_dir>/<map_id>.h5`` (written atomically) and publishes a
   ``built`` event: every replica loads the map;
3. a worker killed mid-build leaves a record ``running`` whose heartbeat stops: after
   ``build_heartbeat_stale_s`` any live worker releases arq's in-progress lock on it and the build runs
   again (``attempts`` + 1, at most ``build_max_tries``); the record is durable as long as Redis persists
   (compose: append-only file);
4. ``DELETE /maps/<id>`` of a map still building cancels it: the record is flagged, the worker stops at
   its next batch, removes the job's files and the record.

States of a record: ``queued``, ``running``, ``ready``, ``failed`` (with ``error``), ``cancelled``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import shutil
import socket
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import numpy as np
import redis

from reradar_core.localization.extractor import FeatureExtractor
from service.core.config import Settings
from service.core.errors import ConflictError
from service.core.registry import MapEntry, MapRegistry, utc_now
from service.core.shared_state import SharedStateUnavailableError, arq_redis_settings

__all__ = ["BuildQueue", "QueuedMapRegistry", "JOB_FUNCTION", "ARQ_IN_PROGRESS_PREFIX", "ARQ_JOB_PREFIX", "jobs_dir"]

logger = logging.getLogger(__name__)

#: Name of the arq function that builds a map (``service.worker``).
JOB_FUNCTION = "build_map"
#: arq's own key prefix for the lock a worker holds on a running job (``arq.constants``).
ARQ_IN_PROGRESS_PREFIX = "arq:in-progress:"
#: arq's key of a queued job's data (``arq.constants.job_key_prefix``)
ARQ_JOB_PREFIX = "arq:job:"

_ACTIVE = ("queued", "running")


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

    # ---- enqueue / cancel ---------------------------------------------------------------------------------
    def enqueue(self, map_id: str, job_id: str, scans_total: int, source: str) -> None:
        """Claim ``map_id`` across every replica, write its record and put the build on the queue.

        Raises:
            ConflictError: another build of ``map_id`` exists. redis.RedisError: Redis is down.
        """
        key = self.keys.build(map_id)
        if not self.redis.hsetnx(key, "job_id", job_id):
            if self.record(map_id).get("cancel") == "1":
                raise ConflictError(f"map {map_id!r}: its cancelled build is stopping (at its next batch); "
                                    "retry in a few seconds")
            raise ConflictError(f"map {map_id!r} is already being built (or its build failed: DELETE "
                                f"/maps/{map_id} first)")
        try:  # from the claim on, a failure frees the id again ("nothing was stored")
            self.update(map_id, map_id=map_id, state="queued", scans_done=0, scans_total=scans_total, attempts=0,
                        error="", worker="", heartbeat=0, cancel=0, source=source, created_utc=utc_now())
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

    def cancel(self, map_id: str) -> tuple[bool, str | None]:
        """Stop building ``map_id``. A build no worker has started is taken off the queue at once (its id is free
        again); a running one is flagged and stops at its next batch.

        Returns:
            (whether a queued or running build was cancelled, the job id when it was taken off the queue: its
            files are the caller's to remove, no worker will).
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
                self.remove(map_id)
                return True, job_id
        self.update(map_id, cancel=1)
        return True, None


class QueuedMapRegistry(MapRegistry):
    """A ``MapRegistry`` whose archive builds go to the job queue and whose view of builds comes from the
    job records (so every replica shows a map being built, with its progress)."""

    def __init__(self, settings: Settings, extractor: FeatureExtractor, queue: BuildQueue,
                 publish: Callable[[str, str], None]) -> None:
        super().__init__(settings, extractor)
        self.queue = queue
        self._publish = publish

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

    def build_note(self, entry: MapEntry) -> str | None:
        """``build_note`` of a ``building`` entry from its job record and the workers' heartbeats (None when
        Redis cannot say: the note is a hint, the state stays what the records last said)."""
        if entry.state != "building":
            return None
        try:
            rec = self.queue.record(entry.map_id)
            if rec.get("state") not in _ACTIVE:
                return None
            return build_note(rec, self.queue.newest_worker_beat(), time.time(),
                              self.settings.build_heartbeat_stale_s)
        except redis.RedisError:
            return None

    def start_build(self, map_id: str, scan_paths: list[Path], poses: np.ndarray, preset: str | None,
                    workdir: Path, source: str) -> MapEntry:
        """Reserve ``map_id``, move ``workdir`` to the shared jobs folder and enqueue its build."""
        first = self._load_scan(scan_paths[0], preset)  # fail fast, synchronously, on unreadable scans
        preset_name = preset or first.preset or "unknown"
        entry = self._reserve(map_id, scans_total=len(scan_paths))
        job_id = uuid.uuid4().hex
        job_dir = jobs_dir(self.maps_dir) / job_id
        try:
            job_dir.mkdir(parents=True)
            os.replace(workdir, job_dir / "work")
            np.save(job_dir / "poses.npy", np.asarray(poses, dtype=np.float64))
            spec = {"map_id": map_id, "job_id": job_id, "preset": preset, "preset_name": preset_name,
                    "source": source, "scans": [str(p.relative_to(workdir)) for p in scan_paths]}
            (job_dir / "spec.json").write_text(json.dumps(spec))
            try:
                self.queue.enqueue(map_id, job_id, len(scan_paths), source)
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
        logger.info("map %s: build queued as job %s (%d scans)", map_id, job_id, len(scan_paths),
                    extra={"map_id": map_id, "job_id": job_id})
        self._publish("queued", map_id)
        return entry

    def delete(self, map_id: str) -> MapEntry:
        """Delete a map; a map still building is cancelled (its job stops at the next batch)."""
        entry = self.get(map_id)
        try:
            cancelled, dropped_job = self.queue.cancel(map_id) if entry.state == "building" else (False, None)
        except redis.RedisError as exc:
            raise SharedStateUnavailableError(
                f"map {map_id!r} is being built and build jobs live in Redis, which is unavailable; retry "
                f"later") from exc
        if cancelled:
            with self._lock:
                self._entries.pop(map_id, None)
            if dropped_job:  # taken off the queue before any worker ran it: its uploaded scans go now
                shutil.rmtree(jobs_dir(self.maps_dir) / dropped_job, ignore_errors=True)
            logger.info("map %s: build cancelled", map_id, extra={"map_id": map_id})
            self._publish("cancelled", map_id)
            return entry
        entry = super().delete(map_id)  # the "deleted" event is published by OpsMiddleware
        try:
            if self.queue.record(map_id).get("state") not in _ACTIVE:
                self.queue.remove(map_id)  # a failed build's record goes with the map
        except redis.RedisError:
            logger.warning("map %s deleted, but its build record could not be removed (Redis down)", map_id)
        return entry

    def _swap_in_built(self, map_id: str) -> None:
        """Replace the ``building`` entry of a finished build by the loaded map, in one step (a request
        never sees the id missing in between)."""
        entry = self._load_entry(map_id, self.path_for(map_id))
        with self._lock:
            current = self._entries.get(map_id)
            if current is None or current.state == "building":
                self._entries[map_id] = entry
                return
        if entry.db is not None:  # someone else loaded it meanwhile
            entry.db.close()

    def reconcile_builds(self) -> None:
        """Mirror the job records into this registry: active builds as ``building`` with their progress,
        failed ones as ``failed`` with the reason; finished ones are loaded by ``MapSync``'s file pass."""
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
            elif state == "failed" and (entry is None or entry.state == "building"):
                failed = MapEntry(map_id, self.path_for(map_id), "failed", error=rec.get("error") or "failed",
                                  scans_done=int(rec.get("scans_done", 0)),
                                  scans_total=int(rec.get("scans_total", 0)))
                with self._lock:
                    self._entries[map_id] = failed
            elif state == "ready" and entry is not None and entry.state == "building":
                self._swap_in_built(map_id)
        # builds that vanished (cancelled and cleaned up) leave no building entry behind
        with self._lock:
            stale = [m for m, e in self._entries.items() if e.db is None and (
                (e.state == "building" and (m not in records or records[m].get("cancel") == "1"))
                # a failed build deleted through another replica: its record is gone and it never had a file
                or (e.state == "failed" and m not in records and not e.path.exists()))]
            for m in stale:
                self._entries.pop(m, None)
