"""``reradar worker``: runs queued map builds (``service.core.jobs``) from the shared Redis.

One worker builds one map at a time (the network uses the CPU cores); run more workers for more parallel
builds. Each worker also watches the job records: a build whose worker stopped sending heartbeats (killed,
machine lost) is released so that a live worker runs it again, and job folders left without a record (Redis
lost its data) are removed (``sweep_orphan_jobs``).

A finished build is installed exclusively (never over a map file registered meanwhile: the build fails) and
then marked ``ready`` only if no DELETE cancelled it (``BuildQueue.mark_ready``); a DELETE that won that race
was answered 200, so the worker removes the map it installed.
"""

from __future__ import annotations

import asyncio
import json
import logging
import shutil
import socket
import threading
import time
from pathlib import Path
from typing import Any, cast

import numpy as np
import redis

from maps.paths import far_view_path
from reradar_core.errors import ReRadarError
from reradar_core.io.poses import PoseSequence
from reradar_core.localization.extractor import FeatureExtractor
from reradar_core.localization.far_view import FarViewConfig
from service.core.archive import pose_file_reader
from service.core.config import Settings
from service.core.errors import scrub_paths
from service.core.jobs import (
    ARQ_IN_PROGRESS_PREFIX,
    ARQ_JOB_PREFIX,
    JOB_FUNCTION,
    POSE_TRACK_FILE,
    BuildQueue,
    identity_text,
    installed_by,
    jobs_dir,
    orphan_job_age_s,
    remove_installed_map,
    sweep_orphan_jobs,
)
from service.core.logs import configure_logging
from service.core.registry import (
    RECORD_TIME_FORMAT,
    MapRegistry,
    build_failure_message,
    file_identity,
    install_map_files,
)
from service.core.shared_state import Keys, arq_redis_settings, connect, replica_id

__all__ = ["run_worker", "build_map_job", "BuildCancelledError", "register"]

logger = logging.getLogger("service.worker")

#: Seconds between a running build's heartbeats.
HEARTBEAT_S = 2.0
#: Seconds between the worker's own health records (``reradar worker --check`` reads them).
HEALTH_S = 10.0
#: wait before a worker that lost Redis connects again, seconds
RECONNECT_S = 2.0


def health_key(keys: Keys) -> str:
    """arq's health record of this worker: ``<namespace>:v1:worker-health:<hostname>`` (one worker per container;
    it expires, so under ``volatile-ttl`` eviction Redis drops it first)."""
    return f"{keys.prefix}:worker-health:{socket.gethostname()}"


def _beat(client: redis.Redis, keys: Keys) -> None:
    # read by ``reradar worker --check`` and by the API's note on a build no worker is taking
    client.hset(keys.worker_heartbeats, socket.gethostname(), f"{time.time():.3f}")


class BuildCancelledError(Exception):
    """The job record asks this build to stop."""


class BuildGaveUpError(Exception):
    """The build was attempted ``build_max_tries`` times (crashed workers count)."""


class MapIdTakenError(Exception):
    """A map file was installed under the build's id while it was being built: the build is discarded."""


def _publish(ctx: dict[str, Any], op: str, map_id: str) -> None:
    try:
        ctx["sync_redis"].publish(ctx["keys"].map_events, json.dumps({"op": op, "map_id": map_id, "origin": ctx["origin"]}))
    except redis.RedisError as exc:
        logger.warning("map event %s %s not published: %s", op, map_id, exc)


def _discard_installed(ctx: dict[str, Any], map_id: str, job_id: str) -> None:
    """Remove the map file an attempt of ``job_id`` installed, if any: its build was cancelled, by a DELETE that
    was answered 200, after the install (``BuildQueue.mark_ready`` lost to ``BuildQueue.cancel``)."""
    rec = ctx["queue"].record(map_id)
    target = ctx["registry"].path_for(map_id)
    if rec.get("job_id") == job_id and remove_installed_map(rec, target):
        _publish(ctx, "deleted", map_id)  # replicas that loaded it meanwhile drop it
        logger.info("map %s: build cancelled after its install; map removed", map_id, extra={"map_id": map_id})


def _finish(ctx: dict[str, Any], map_id: str, job_id: str, scans_done: int) -> str:
    """Mark the build whose map is installed ``ready``, unless a DELETE cancelled it meanwhile (atomic:
    ``BuildQueue.mark_ready``; the cancel handler then removes the map). Returns ``ready``."""
    outcome = ctx["queue"].mark_ready(map_id, job_id, scans_done)
    if outcome == 0:
        raise BuildCancelledError
    if outcome < 0:
        logger.warning("map %s: its build record is gone or belongs to another job (Redis lost its data?); the "
                       "built map is kept", map_id, extra={"map_id": map_id, "job_id": job_id})
    shutil.rmtree(jobs_dir(ctx["registry"].maps_dir) / job_id, ignore_errors=True)
    _publish(ctx, "built", map_id)
    logger.info("map %s built", map_id, extra={"map_id": map_id, "job_id": job_id})
    return "ready"


def _build(ctx: dict[str, Any], map_id: str, job_id: str) -> str:
    """The blocking part of a build job (runs in a thread). Returns the final state."""
    from maps.build import build_map

    settings: Settings = ctx["settings"]
    queue: BuildQueue = ctx["queue"]
    registry: MapRegistry = ctx["registry"]
    job_dir = jobs_dir(registry.maps_dir) / job_id
    rec = queue.record(map_id)
    if rec.get("job_id") != job_id:
        logger.warning("job %s: record of map %s belongs to job %s; dropping", job_id, map_id, rec.get("job_id"))
        shutil.rmtree(job_dir, ignore_errors=True)
        return "superseded"
    if rec.get("cancel") == "1":
        raise BuildCancelledError
    if rec.get("state") == "ready":  # finished by a worker that was stopped (SIGTERM) after arq re-queued the job
        logger.info("job %s: map %s is built already; nothing to do", job_id, map_id)
        return "ready"
    target = registry.path_for(map_id)
    if installed_by(rec, target):  # an earlier attempt installed it and stopped (killed, Redis hiccup) before
        logger.info("job %s: map %s was installed by an earlier attempt", job_id, map_id)
        return _finish(ctx, map_id, job_id, int(rec.get("scans_total") or 0))
    spec = json.loads((job_dir / "spec.json").read_text())
    poses = np.load(job_dir / "poses.npy")
    pose_at = None
    if (job_dir / POSE_TRACK_FILE).is_file():
        with np.load(job_dir / POSE_TRACK_FILE) as saved:
            track = PoseSequence(saved["timestamps_us"], saved["xy"], saved["yaw"])
        pose_at = pose_file_reader(track, spec["preset"])
    scans = [job_dir / "work" / rel for rel in spec["scans"]]
    attempts = int(queue.redis.hincrby(queue.keys.build(map_id), "attempts", 1))  # type: ignore[arg-type]
    if attempts > settings.build_max_tries:
        last = (rec.get("error") or "worker lost").removesuffix("; retrying")
        raise BuildGaveUpError(f"gave up after {attempts - 1} attempts (the last: {last}); the uploaded scans are "
                               f"gone: DELETE /maps/{map_id} and register the map again")
    queue.update(map_id, state="running", worker=ctx["origin"], heartbeat=time.time(), scans_done=0)
    logger.info("map %s: building job %s, attempt %d, %d scans", map_id, job_id, attempts, len(scans),
                extra={"map_id": map_id, "job_id": job_id})
    stop = threading.Event()

    def beat() -> None:
        while not stop.wait(HEARTBEAT_S):
            try:
                queue.update(map_id, heartbeat=time.time())
            except redis.RedisError as exc:
                logger.warning("heartbeat of %s failed: %s", map_id, exc)

    beater = threading.Thread(target=beat, daemon=True, name=f"heartbeat-{map_id}")
    beater.start()
    last_event = [0.0]

    def progress(done: int, total: int) -> None:
        try:  # best effort: a Redis stall mid-build must not cost the attempt (the install checks again)
            queue.update(map_id, scans_done=done, heartbeat=time.time())
            cancelled = queue.record(map_id).get("cancel") == "1"
        except redis.RedisError as exc:
            logger.warning("map %s: progress not recorded (Redis: %s); building on", map_id, exc,
                           extra={"map_id": map_id, "job_id": job_id})
            return
        if cancelled:
            raise BuildCancelledError
        if time.monotonic() - last_event[0] >= 1.0:  # replicas refresh their progress view on events
            last_event[0] = time.monotonic()
            _publish(ctx, "progress", map_id)

    # written inside the job folder, then installed: replicas starting meanwhile clean up temporary map files
    # of processes they cannot see (other containers), which must not include a build in progress
    built = job_dir / f"{map_id}.h5"
    far_view = bool(spec.get("far_view"))  # with the far-view companion (POST /maps far_view=true)
    try:
        build_map(built, ctx["extractor"],
                  registry.build_scan_loader(scans, spec["preset"]), poses,
                  radar_preset=spec["preset_name"], name=map_id, source=spec["source"],
                  batch_size=settings.build_batch_size, progress=progress, overwrite=True,
                  localization=settings.localization,  # the place repetition under the settings that serve it
                  far_view=FarViewConfig() if far_view else None, pose_at=pose_at)
        if queue.record(map_id).get("cancel") == "1":  # a DELETE during the last batch: nothing to install
            raise BuildCancelledError
        # recorded first, so a retry after a stop between the install and ``ready`` knows the file as its own
        queue.update(map_id, installed=identity_text(file_identity(built)))
        try:  # the map is the commit point; its companion is beside it by then (``install_map_files``)
            install_map_files(built, target, far_view_path(built) if far_view else None)
        except FileExistsError:
            raise MapIdTakenError(
                f"another map was registered as {map_id!r} while this one was being built, so the built map was "
                f"discarded; DELETE /maps/{map_id} and register it again to replace that map") from None
    finally:
        stop.set()
        beater.join(timeout=5)
    return _finish(ctx, map_id, job_id, len(scans) * (2 if far_view else 1))


async def build_map_job(ctx: dict[str, Any], map_id: str, job_id: str) -> str:
    """arq job: build ``map_id`` from the files of ``job_id``; retried after a crash (see module doc)."""
    from arq import Retry

    queue: BuildQueue = ctx["queue"]
    settings: Settings = ctx["settings"]
    job_dir = jobs_dir(ctx["registry"].maps_dir) / job_id
    try:
        return await asyncio.to_thread(_build, ctx, map_id, job_id)
    except BuildCancelledError:
        _discard_installed(ctx, map_id, job_id)  # the DELETE was answered 200: the map must not stay
        shutil.rmtree(job_dir, ignore_errors=True)
        queue.remove(map_id)
        _publish(ctx, "cancelled", map_id)
        logger.info("map %s: build cancelled", map_id, extra={"map_id": map_id, "job_id": job_id})
        return "cancelled"
    except (BuildGaveUpError, MapIdTakenError) as exc:
        _fail(ctx, map_id, job_dir, str(exc))
        return "failed"
    except (ReRadarError, ValueError, OSError) as exc:
        # bad input (unreadable scan, wrong shape, disk full): retrying cannot help
        _fail(ctx, map_id, job_dir, build_failure_message(exc))
        return "failed"
    except Exception as exc:
        # the record lives in Redis, whose hiccup may be what failed the attempt: its calls are best effort,
        # the Retry is not (a RedisError escaping here would end the arq job for good, its record "queued")
        try:
            attempts = int(queue.record(map_id).get("attempts", "1"))
        except redis.RedisError:
            attempts = int(ctx.get("job_try", 1))
        if attempts < settings.build_max_tries:
            logger.exception("map %s: build attempt %d failed; retrying", map_id, attempts)
            try:
                queue.update(map_id, state="queued", error=f"attempt {attempts}: {build_failure_message(exc)}")
            except redis.RedisError:
                logger.warning("map %s: the build record could not be updated (Redis); retrying anyway", map_id)
            raise Retry(defer=2) from exc
        _fail(ctx, map_id, job_dir, f"{build_failure_message(exc)} (after {attempts} attempts)")
        return "failed"


def _fail(ctx: dict[str, Any], map_id: str, job_dir: Path, error: str) -> None:
    logger.error("map %s: build failed: %s", map_id, error, extra={"map_id": map_id})
    # the record is public (GET /maps/{id}): no server paths in it
    ctx["queue"].update(map_id, state="failed", error=scrub_paths(error, [ctx["registry"].maps_dir]))
    shutil.rmtree(job_dir, ignore_errors=True)
    _publish(ctx, "failed", map_id)


def _created_s(rec: dict[str, str]) -> float:
    """A build record's creation time, seconds since the epoch (0 when unreadable: old enough)."""
    import datetime as dt

    try:
        return dt.datetime.strptime(rec.get("created_utc", ""), RECORD_TIME_FORMAT).replace(
            tzinfo=dt.UTC).timestamp()
    except ValueError:
        return 0.0


def release_stale_builds(queue: BuildQueue, stale_after_s: float, now: float | None = None) -> list[str]:
    """Release arq's lock on running builds whose heartbeat is older than ``stale_after_s`` (their worker
    died), so that the queue hands them out again. Returns the map ids released."""
    now = time.time() if now is None else now
    released = []
    for map_id, rec in queue.records().items():
        job_id = rec.get("job_id", "")
        if (rec.get("state") == "queued" and job_id and rec.get("cancel") != "1"
                and now - _created_s(rec) > stale_after_s
                and not queue.redis.exists(ARQ_JOB_PREFIX + job_id, ARQ_IN_PROGRESS_PREFIX + job_id)):
            # queued, but arq holds no job for it any more (a Redis interruption ended the job): nobody will
            # build it; say so and free nothing silently
            queue.update(map_id, state="failed", error="its queue entry was lost (a Redis interruption during "
                         f"the build); DELETE /maps/{map_id} and register the map again")
            logger.error("map %s: queued build has no queue entry; marked failed", map_id, extra={"map_id": map_id})
            continue
        if rec.get("state") != "running":
            continue
        if now - float(rec.get("heartbeat") or 0.0) < stale_after_s:
            continue
        queue.redis.delete(ARQ_IN_PROGRESS_PREFIX + job_id)
        queue.update(map_id, state="queued", error=f"worker {rec.get('worker')} stopped responding; retrying")
        logger.warning("map %s: worker %s stopped responding; build released for a retry", map_id,
                       rec.get("worker"), extra={"map_id": map_id, "job_id": job_id})
        released.append(map_id)
    return released


def load_build_extractor(settings: Settings) -> FeatureExtractor:
    """The descriptor model a build worker builds with (``settings.model``), loaded after the log format is set
    (the loader logs which network runtime it chose) at the worker's thread counts (RERADAR_TORCH_THREADS,
    RERADAR_BLAS_THREADS: an ONNX Runtime session is created at torch's count). ``reradar worker`` loads it so
    before the worker starts, which is its check of RERADAR_MODEL too, and hands it to ``run_worker``.

    Raises:
        ReRadarError: unknown model name, missing, unreadable or mismatched weights.
    """
    from reradar_core.localization.extractor import load_default_extractor
    from service.core.blas import limit_threads

    configure_logging(settings.log_level, settings.log_format)
    limit_threads(settings)
    return load_default_extractor(settings.model)


def run_worker(settings: Settings, extractor: FeatureExtractor | None = None, burst: bool = False) -> None:
    """Run a build worker until SIGINT/SIGTERM (``burst``: until the queue is empty). ``extractor``: the model to
    build with (default: ``load_build_extractor``; ``reradar worker`` passes the one it loaded)."""
    from arq.worker import Worker, func

    configure_logging(settings.log_level, settings.log_format)
    if not settings.redis_url:
        raise ValueError("the worker needs RERADAR_REDIS_URL (the queue lives in Redis)")
    if extractor is None:
        extractor = load_build_extractor(settings)
    client = connect(settings.redis_url)
    keys = Keys(settings.redis_namespace)
    queue = BuildQueue(client, keys, settings)
    # arq puts its own asyncio pool under ctx["redis"]; the build thread uses this blocking client
    ctx: dict[str, Any] = {"settings": settings, "queue": queue, "sync_redis": client, "keys": keys,
                           "registry": MapRegistry(settings, extractor), "extractor": extractor,
                           "origin": replica_id()}
    stop = threading.Event()
    orphan_age_s = orphan_job_age_s(settings)

    def reaper() -> None:
        last_sweep = 0.0
        while True:
            try:
                _beat(client, keys)
                release_stale_builds(queue, settings.build_heartbeat_stale_s)
                if time.monotonic() - last_sweep >= 60.0:  # folders are only removed minutes after their record
                    sweep_orphan_jobs(queue, ctx["registry"].maps_dir, orphan_age_s)
                    last_sweep = time.monotonic()
            except redis.RedisError as exc:
                logger.warning("stale-build check failed: %s", exc)
            if stop.wait(min(HEALTH_S / 2, settings.build_heartbeat_stale_s / 3)):
                return

    threading.Thread(target=reaper, daemon=True, name="build-reaper").start()
    logger.info("worker %s ready: queue %s, maps in %s, model %s", ctx["origin"], keys.queue,
                settings.maps_dir, extractor.model_id)
    try:
        while True:
            worker = Worker(
                functions=[func(build_map_job, name=JOB_FUNCTION, timeout=settings.build_job_timeout_s,  # type: ignore[arg-type]
                                max_tries=settings.build_max_tries + 2)],  # our record counts attempts
                queue_name=keys.queue, redis_settings=arq_redis_settings(settings.redis_url), ctx=ctx,
                max_jobs=1, poll_delay=0.5, burst=burst, keep_result=3600, handle_signals=True,
                health_check_interval=HEALTH_S, health_check_key=health_key(keys),
            )
            try:
                worker.run()  # returns on SIGINT / SIGTERM (or an empty queue with ``burst``)
                break
            except (redis.RedisError, OSError) as exc:
                # Redis restarted or unreachable: wait and reconnect like the API does, instead of exiting (a
                # build in progress is released by the stale-build check and runs again)
                if burst:
                    raise
                logger.error("worker %s lost Redis (%s: %s); reconnecting in %.0f s", ctx["origin"],
                             type(exc).__name__, exc, RECONNECT_S)
                time.sleep(RECONNECT_S)
    finally:
        stop.set()
        client.close()


def check_health(settings: Settings, now: float | None = None) -> bool:
    """True when this host's worker recorded a sign of life within the last ``HEALTH_S`` + 1 seconds."""
    try:
        value = connect(settings.redis_url or "").hget(Keys(settings.redis_namespace).worker_heartbeats,
                                                       socket.gethostname())
    except redis.RedisError:
        return False
    try:
        last = float(cast(bytes, value)) if value is not None else 0.0
    except ValueError:
        return False
    return (time.time() if now is None else now) - last <= HEALTH_S + 1


def worker_command(check: bool = False) -> None:
    """Run a map-build worker (needs RERADAR_REDIS_URL; settings from RERADAR_* variables).

    Exit status: 2 for invalid settings (no, or a malformed, RERADAR_REDIS_URL or credentials Redis refuses; an
    unknown RERADAR_MODEL), 3 when Redis cannot be reached; ``check``: 0 when this host's worker is alive, else 1
    (with a message when Redis cannot be reached)."""
    import typer

    from service.cli import check_redis_credentials_or_exit, served_model_or_exit, settings_or_exit

    settings = settings_or_exit()
    if not settings.redis_url:
        typer.echo("error: set RERADAR_REDIS_URL (e.g. redis://127.0.0.1:6379/0): the build queue lives in Redis",
                   err=True)
        raise typer.Exit(2)
    # one PING: refused credentials are a setting (2), an unreachable Redis an outage (3; 1 for --check); a
    # malformed URL was refused by the settings already
    check_redis_credentials_or_exit(settings, unreachable_exit=1 if check else 3)
    if check:
        if check_health(settings):
            raise typer.Exit(0)
        typer.echo(f"no live worker on this host: its health record in Redis is older than {HEALTH_S + 1:.0f} s "
                   "or missing (start `reradar worker`)", err=True)
        raise typer.Exit(1)
    # one load: the check of RERADAR_MODEL (one line, exit 2) is the load the worker builds with
    run_worker(settings, served_model_or_exit(settings, load_build_extractor))


def register(app: Any) -> None:
    """Add ``worker`` to the ``reradar`` command line."""
    import typer

    def worker(check: bool = typer.Option(False, "--check", help=(
            "Exit 0 if this host's worker is alive (its health record in Redis is fresh), 1 if it is not or Redis "
            "cannot be reached (with a message), 2 if the settings are invalid (RERADAR_REDIS_URL unset or "
            "malformed, or credentials Redis refuses)."))) -> None:
        """Run a map-build worker: queued builds from Redis (needs RERADAR_REDIS_URL; docs/OPERATIONS.md)."""
        worker_command(check)

    app.command("worker")(worker)
