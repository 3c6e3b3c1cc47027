"""State shared by every replica of the service, on Redis (optional: one process keeps it in memory).

What lives in Redis (keys ``<namespace>:v1:...``; ``v1`` changes when a value's encoding does):

| key | type | what |
| --- | --- | --- |
| ``scan:<scan_id>`` | string, TTL ``scan_cache_ttl_s`` | features of an uploaded scan (``encode_features``) |
| ``recent:<map_id>`` | list, newest first, capped | the latest localizations on a map (JSON) |
| ``session:<map_id>:<session_id>`` | string, TTL ``session_ttl_s`` | a tracking session's pose prior (JSON) |
| ``maps:events`` | pub/sub channel | ``{"op", "map_id", "origin"}`` when a map is registered, built or deleted |
| ``build:<map_id>``, ``builds``, ``queue`` | hash, set, arq queue | map build jobs (``service.core.jobs``) |

Every replica listens on ``maps:events`` and reconciles its registry with the shared maps folder: a map file
that appeared is loaded, a map whose file is gone is dropped, a map whose file was replaced (deleted and
registered again) is reopened (within a second of the event; a full re-check every ``map_sync_interval_s``
catches missed events). Redis down: uploading or using a ``scan_id`` answers
503, everything else - localizing inline scans on the maps already loaded - keeps working.
"""

from __future__ import annotations

import io
import json
import logging
import os
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
import redis

from maps.database import FAR_VIEW
from reradar_core.errors import ReRadarError
from reradar_core.features import ScanFeatures
from reradar_core.localization import PosePrior
from service.core.config import Settings, redis_url_parts
from service.core.errors import ServiceError, ServiceUnavailableError
from service.core.registry import MapRegistry
from service.core.scan_cache import CachedScan, ScanCache, new_scan_id
from service.core.sessions import SessionConfig, SessionStore

__all__ = ["Keys", "SharedStateUnavailableError", "RedisScanStore", "RedisSessionStore", "RecentLocalizations", "MapSync",
           "OpsRuntime", "encode_features", "decode_features", "replica_id"]

logger = logging.getLogger(__name__)

#: Version of the key layout and value encodings; bump it when either changes.
SCHEMA_VERSION = "v1"


def replica_id() -> str:
    """This process' name in events and records: ``<hostname>:<pid>``."""
    return f"{socket.gethostname()}:{os.getpid()}"


class SharedStateUnavailableError(ServiceUnavailableError):
    """Redis (fleet mode) is unreachable or refuses the write: a 503 with ``Retry-After`` (docs/SERVICE.md)."""

    code = "shared_state_unavailable"


@dataclass(frozen=True)
class Keys:
    """Redis key names of one deployment (``namespace``) and schema version."""

    namespace: str = "reradar"

    @property
    def prefix(self) -> str:
        return f"{self.namespace}:{SCHEMA_VERSION}"

    def scan(self, scan_id: str) -> str:
        return f"{self.prefix}:scan:{scan_id}"

    def recent(self, map_id: str) -> str:
        return f"{self.prefix}:recent:{map_id}"

    def session(self, session_id: str, map_id: str) -> str:
        return f"{self.prefix}:session:{map_id}:{session_id}"

    @property
    def map_events(self) -> str:
        return f"{self.prefix}:maps:events"

    def build(self, map_id: str) -> str:
        return f"{self.prefix}:build:{map_id}"

    @property
    def builds(self) -> str:
        return f"{self.prefix}:builds"

    @property
    def queue(self) -> str:
        return f"{self.prefix}:queue"

    @property
    def worker_heartbeats(self) -> str:
        """Hash of the build workers' last signs of life (field: hostname, value: Unix time). It has no TTL, so
        a full Redis under ``volatile-ttl`` never evicts it."""
        return f"{self.prefix}:worker-heartbeats"


def arq_redis_settings(url: str) -> Any:
    """arq's ``RedisSettings`` for ``url``, from ``redis_url_parts`` (arq's own ``from_dsn`` does not decode a
    percent-encoded password and fails on paths redis-py accepts: one parser for both clients)."""
    from arq.connections import RedisSettings
    from redis.connection import SSLConnection

    parts = redis_url_parts(url)
    return RedisSettings(host=parts.get("host", "localhost"), port=int(parts.get("port", 6379)),
                         unix_socket_path=parts.get("path"), database=int(parts.get("db", 0)),
                         username=parts.get("username"), password=parts.get("password"),
                         ssl=parts.get("connection_class") is SSLConnection)


def connect(url: str) -> redis.Redis:
    """A Redis client with short timeouts: a dead Redis must answer 503 quickly, not hang requests."""
    return redis.Redis.from_url(url, socket_timeout=2.0, socket_connect_timeout=2.0, health_check_interval=15)


# ---- uploaded scans --------------------------------------------------------------------------------------
def encode_features(features: ScanFeatures, preset: str | None, preset_open: bool = False,
                    far_features: ScanFeatures | None = None, dense_image: np.ndarray | None = None) -> bytes:
    """``ScanFeatures`` + preset (and whether the scan left it open: ``CachedScan.preset_open``), the far view's
    features when given (``CachedScan.far_features``, keys ``far_*``) and its dense image (``CachedScan.dense_image``,
    float16, ~130 KB at 257 px), as an ``.npz`` blob (no pickle): ~90 KB for 1200 keypoints x 32 float16."""
    extra: dict[str, Any] = {} if far_features is None else {
        "far_global_descriptor": far_features.global_descriptor, "far_keypoints_xy_m": far_features.keypoints_xy_m,
        "far_local_descriptors": far_features.local_descriptors}
    if dense_image is not None:
        extra["dense_image"] = np.asarray(dense_image, np.float16)
    buf = io.BytesIO()
    np.savez(buf, global_descriptor=features.global_descriptor, keypoints_xy_m=features.keypoints_xy_m,
             local_descriptors=features.local_descriptors, timestamp_us=np.int64(features.timestamp_us),
             preset=np.array(preset or ""), preset_open=np.bool_(preset_open), **extra)
    return buf.getvalue()


#: Largest element count ``decode_features`` reads from one array of a stored scan (4 Mi: 65,536 keypoints x 64
#: local descriptor channels; the service stores at most the extractor's keypoint cap, 512 by default, x 32; a dense
#: image is 257 x 257): an entry declaring more is unreadable.
MAX_STORED_ARRAY_ELEMENTS = 1 << 22


def _stored_array(z: Any, name: str) -> np.ndarray:
    """Array ``name`` of an ``.npz``, its header checked before its data is read (a small entry declaring a huge
    array, or compressed 1000:1, must not allocate it): ValueError when it declares more than
    ``MAX_STORED_ARRAY_ELEMENTS`` or holds objects."""
    with z.zip.open(f"{name}.npy") as fh:
        version = np.lib.format.read_magic(fh)
        shape, _, dtype = (np.lib.format.read_array_header_1_0(fh) if version == (1, 0)
                           else np.lib.format.read_array_header_2_0(fh))
    if dtype.hasobject or int(np.prod(shape, dtype=np.float64)) > MAX_STORED_ARRAY_ELEMENTS:
        raise ValueError(f"stored array {name} declares {shape} {dtype}")
    return np.asarray(z[name])


def decode_features(blob: bytes) -> tuple[ScanFeatures, str | None, bool, ScanFeatures | None, np.ndarray | None]:
    """Inverse of ``encode_features`` (a blob of an earlier version, without ``preset_open``: False; without far
    features or a dense image: None). A dense image that is not a finite (W, W) float image of the far view's
    width W (257 px) once stored as float16 is dropped (None): another version's would not correlate. Every array's
    header is checked before its data is read (``_stored_array``): ValueError for one too large."""
    with np.load(io.BytesIO(blob), allow_pickle=False) as z:
        features = ScanFeatures(_stored_array(z, "global_descriptor"), _stored_array(z, "keypoints_xy_m"),
                                _stored_array(z, "local_descriptors"), int(_stored_array(z, "timestamp_us")))
        preset = str(z["preset"]) or None
        preset_open = bool(z["preset_open"]) if "preset_open" in z.files else False
        far = None
        if "far_global_descriptor" in z.files:
            far = ScanFeatures(_stored_array(z, "far_global_descriptor"), _stored_array(z, "far_keypoints_xy_m"),
                               _stored_array(z, "far_local_descriptors"), int(_stored_array(z, "timestamp_us")))
        dense = None
        if "dense_image" in z.files:
            d = _stored_array(z, "dense_image")
            w = FAR_VIEW.cartesian.width_px
            if d.shape == (w, w) and d.dtype.kind == "f":
                with np.errstate(over="ignore", invalid="ignore"):
                    d16 = d.astype(np.float16)
                dense = d16 if np.isfinite(d16).all() else None
    return features, preset, preset_open, far, dense


def _json_record(raw: bytes) -> dict[str, Any] | None:
    """One JSON object of a Redis list, or None for a value this version cannot read (skipped, never a 500)."""
    try:
        item = json.loads(raw)
    except ValueError:
        return None
    return item if isinstance(item, dict) else None


class RedisScanStore(ScanCache):
    """Uploaded scans' features in Redis, seen by every replica; each expires ``ttl_s`` after upload.

    Redis bounds memory with its own ``maxmemory`` policy (compose: ``volatile-ttl``), so there is no entry
    bound here (nor a per-caller one: entries live out their TTL). Keys name the uploader, so another caller's
    ``scan_id`` is not found. ``len()`` is 0: this process holds no scans.
    """

    def __init__(self, client: redis.Redis, keys: Keys, ttl_s: float) -> None:
        super().__init__(max_entries=1, ttl_s=ttl_s)
        self._redis = client
        self._keys = keys

    def put(self, features: ScanFeatures, preset: str | None, preset_open: bool = False,
            far_features: ScanFeatures | None = None, owner: str = "loopback",
            dense_image: np.ndarray | None = None) -> CachedScan:
        entry = CachedScan(new_scan_id(), features, preset, preset_open, far_features, owner, dense_image)
        try:
            # the key names the uploader: another caller's scan_id is not found (``ScanCache``)
            self._redis.set(self._keys.scan(f"{owner}:{entry.scan_id}"),
                            encode_features(features, preset, preset_open, far_features, dense_image),
                            px=int(self.ttl_s * 1000))
        except redis.RedisError as exc:
            raise SharedStateUnavailableError(
                "the shared scan store (Redis) is unavailable, so the scan was not stored; send the scan "
                "inline (multipart) to POST /localize instead, or retry later") from exc
        return entry

    def get(self, scan_id: str, owner: str = "loopback") -> CachedScan | None:
        try:
            blob = cast(bytes | None, self._redis.get(self._keys.scan(f"{owner}:{scan_id}")))
        except redis.RedisError as exc:
            raise SharedStateUnavailableError(
                "the shared scan store (Redis) is unavailable, so scan_id cannot be resolved; send the scan "
                "inline (multipart) instead, or retry later") from exc
        if blob is None:
            return None
        try:
            features, preset, preset_open, far, dense = decode_features(blob)
        except (ValueError, KeyError, TypeError, OSError, ReRadarError):  # not a value this version wrote
            logger.warning("scan %s: unreadable value in the shared scan store; treated as unknown", scan_id)
            return None
        return CachedScan(scan_id, features, preset, preset_open, far, owner, dense)

    def __len__(self) -> int:
        return 0


class RedisSessionStore(SessionStore):
    """Tracking sessions in Redis, so consecutive scans of one vehicle may reach any worker or replica: one
    JSON value per (session, map) that expires ``ttl_s`` after its last update (Redis' ``maxmemory`` policy
    bounds their number, not ``max_sessions``). Redis down: the session is forgotten for that scan (it is
    localized globally, as after a session's expiry) - localizing never fails because of it."""

    #: after a failed call, sessions skip Redis this long (seconds): a hung Redis costs each tracked scan two
    #: 2 s timeouts otherwise, while it holds one of the replica's request slots
    BACKOFF_S = 5.0

    def __init__(self, client: redis.Redis, keys: Keys, config: SessionConfig | None = None) -> None:
        super().__init__(config)
        self._redis = client
        self._keys = keys
        self._skip_until = 0.0

    def _failed(self, session_id: str, what: str) -> None:
        if time.monotonic() >= self._skip_until:
            logger.warning("tracking session %s: Redis unavailable, %s (sessions skip Redis for %.0f s)",
                           session_id, what, self.BACKOFF_S)
        self._skip_until = time.monotonic() + self.BACKOFF_S

    def get(self, session_id: str, map_id: str) -> PosePrior | None:
        if time.monotonic() < self._skip_until:
            return None
        try:
            blob = cast(bytes | None, self._redis.get(self._keys.session(session_id, map_id)))
        except redis.RedisError:
            self._failed(session_id, "localizing globally")
            return None
        if blob is None:
            return None
        try:
            item = json.loads(blob)
            # the scan time is absent in values written before session 30; ``PosePrior`` checks it is an int64
            return PosePrior(np.array(item["pose"], np.float64), float(item["sigma_xy_m"]),
                             float(item["sigma_yaw_rad"]), item.get("timestamp_us"))
        except (ValueError, KeyError, TypeError, OverflowError, ReRadarError):  # e.g. a time of 1e400
            return None  # a value this version cannot read: start the session afresh

    def _store(self, session_id: str, map_id: str, state: PosePrior) -> None:
        value = json.dumps({"pose": [float(v) for v in state.T_map_query], "sigma_xy_m": state.sigma_xy_m,
                            "sigma_yaw_rad": state.sigma_yaw_rad, "timestamp_us": state.timestamp_us})
        if time.monotonic() < self._skip_until:
            return
        try:
            self._redis.set(self._keys.session(session_id, map_id), value, px=int(self.config.ttl_s * 1000))
        except redis.RedisError:
            self._failed(session_id, "pose not kept")

    def __len__(self) -> int:
        return 0


# ---- recent localizations ---------------------------------------------------------------------------------
class RecentLocalizations:
    """The latest localizations per map, newest first: in Redis when given a client, else in memory.

    Records are JSON-able dicts (``service.api.ops_middleware`` writes them). Failures to write are logged
    and dropped: the operator page must never break localization.
    """

    def __init__(self, capacity: int, client: redis.Redis | None = None, keys: Keys | None = None) -> None:
        self.capacity = capacity
        self._redis = client
        self._keys = keys or Keys()
        self._local: dict[str, deque[dict[str, Any]]] = {}
        self._lock = threading.Lock()

    def add(self, map_id: str, record: dict[str, Any]) -> None:
        if self._redis is not None:
            try:
                pipe = self._redis.pipeline()
                pipe.lpush(self._keys.recent(map_id), json.dumps(record))
                pipe.ltrim(self._keys.recent(map_id), 0, self.capacity - 1)
                pipe.execute()
            except redis.RedisError as exc:
                logger.warning("recent localization not recorded (Redis: %s)", exc)
            return
        with self._lock:
            self._local.setdefault(map_id, deque(maxlen=self.capacity)).appendleft(record)

    def latest(self, map_id: str, limit: int) -> list[dict[str, Any]]:
        """Up to ``limit`` records of ``map_id``, newest first.

        Raises:
            SharedStateUnavailableError: Redis is configured but down.
        """
        limit = max(0, min(limit, self.capacity))
        if limit == 0:  # LRANGE 0 -1 would be the whole list
            return []
        if self._redis is not None:
            try:
                raw = cast(list[bytes], self._redis.lrange(self._keys.recent(map_id), 0, limit - 1))
            except redis.RedisError as exc:
                raise SharedStateUnavailableError(
                    "recent localizations live in Redis, which is unavailable; retry later") from exc
            return [item for item in map(_json_record, raw) if item is not None]
        with self._lock:
            return list(self._local.get(map_id, ()))[:limit]

    def drop(self, map_id: str) -> None:
        if self._redis is not None:
            try:
                self._redis.delete(self._keys.recent(map_id))
            except redis.RedisError:
                pass
            return
        with self._lock:
            self._local.pop(map_id, None)


def reconcile_with_folder(registry: MapRegistry, extra: Callable[[], None] | None = None) -> None:
    """One pass of bringing ``registry`` in step with its maps folder: a map file without a registry entry is
    loaded (``MapRegistry.adopt``), a ready entry (or one that failed to open its file) whose file is gone is
    dropped (``MapRegistry.forget``), and one whose file is another file than the one it opened is reopened
    (``MapRegistry.reopen_if_replaced``). ``extra`` (the build jobs' view) runs after it."""
    # is_file follows a link: one whose target is gone is no map on disk (QA session 41: still served)
    on_disk = {p.stem for p in registry.maps_dir.glob("*.h5") if _valid_id(registry, p.stem) and p.is_file()}
    known = {e.map_id: e for e in registry.entries()}
    for map_id in sorted(on_disk - known.keys()):
        with _one_map(map_id, "load"):
            entry = registry.adopt(map_id)
            if entry is not None:
                logger.info("map %s loaded from the maps folder (%s)", map_id, entry.state, extra={"map_id": map_id})
    for map_id, entry in known.items():
        # a loaded map whose file is gone was deleted elsewhere; a failed build never had a file (its entry
        # follows its build record: ``reconcile_builds``)
        from_file = entry.state == "ready" or (entry.state == "failed" and entry.file_id is not None)
        with _one_map(map_id, "re-check"):
            if from_file and map_id not in on_disk and not entry.path.exists():
                if registry.forget(map_id, entry) is None:
                    continue  # registered again since the pass looked
                logger.info("map %s dropped: its file was deleted by another process", map_id,
                            extra={"map_id": map_id})
            elif from_file and (new := registry.reopen_if_replaced(map_id)) is not None:
                logger.info("map %s reopened: its file was replaced by another process (%s)", map_id, new.state,
                            extra={"map_id": map_id})
    if extra is not None:
        extra()


@contextmanager
def _one_map(map_id: str, what: str) -> Iterator[None]:
    """One map's step of a folder pass: its failure is logged and the pass goes on with the other maps (QA session
    41: one file the registry refused stopped every pass, so maps copied in later were never loaded and removed
    ones kept being served)."""
    try:
        yield
    except Exception as exc:  # noqa: BLE001 - one file must not stop the folder's other maps
        said = f"could not {what} map {map_id}: {exc}"
        # once per problem, not every pass (debug after that)
        level = logging.DEBUG if _FOLDER_PASS_PROBLEMS.get(map_id) == said else logging.WARNING
        _FOLDER_PASS_PROBLEMS[map_id] = said
        logger.log(level, "maps folder pass: %s", said, extra={"map_id": map_id})
    else:
        _FOLDER_PASS_PROBLEMS.pop(map_id, None)


#: the last problem a folder pass logged per map id (``_one_map``)
_FOLDER_PASS_PROBLEMS: dict[str, str] = {}


class FolderSync:
    """One process without Redis: re-reads the maps folder every ``interval_s`` (``reconcile_with_folder``), so a
    map copied in, deleted or rebuilt in place by hand (``reradar build-map --out <maps>/<id>.h5 --overwrite``)
    is served, dropped or reopened within that time instead of at the next start (QA session 40)."""

    def __init__(self, registry: MapRegistry, interval_s: float) -> None:
        self._registry = registry
        self._interval_s = interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="map-folder-sync", daemon=True)
        self.passes = 0

    def _run(self) -> None:
        while not self._stop.wait(self._interval_s):
            try:
                reconcile_with_folder(self._registry)
                self.passes += 1
            except Exception:  # noqa: BLE001 - never let the sync thread die
                logger.exception("maps folder pass failed")

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


# ---- map registry events -------------------------------------------------------------------------------------
class MapSync:
    """Keeps this replica's registry in step with the shared maps folder, driven by Redis events.

    A background thread listens on ``maps:events``; on any event, and every ``interval_s`` regardless, it
    reconciles: a map file without a registry entry is loaded (``MapRegistry.adopt``), a ready entry (or one
    that failed to open its file) whose file is gone is dropped (``MapRegistry.forget``), and one whose file
    is another file than the one it opened is reopened (``MapRegistry.reopen_if_replaced``: a DELETE and a
    new POST of the id elsewhere while this replica missed both events, e.g. it was paused).
    ``extra_reconcile`` (the build jobs' view) runs after each pass.
    """

    def __init__(self, client: redis.Redis, keys: Keys, registry: MapRegistry, interval_s: float,
                 origin: str, extra_reconcile: Callable[[], None] | None = None) -> None:
        self._redis = client
        self._keys = keys
        self._registry = registry
        self._interval_s = interval_s
        self._origin = origin
        self._extra = extra_reconcile
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="map-sync", daemon=True)
        self.passes = 0

    def publish(self, op: str, map_id: str) -> None:
        """Tell every replica that ``map_id`` was registered, built, failed or deleted (best effort)."""
        try:
            self._redis.publish(self._keys.map_events,
                                json.dumps({"op": op, "map_id": map_id, "origin": self._origin}))
        except redis.RedisError as exc:
            logger.warning("map event %s %s not published (Redis: %s); replicas catch up within %.0f s",
                           op, map_id, exc, self._interval_s)

    def reconcile(self) -> None:
        reconcile_with_folder(self._registry, self._extra)
        self.passes += 1

    def _run(self) -> None:
        pubsub = None
        last_full = 0.0
        down = False  # an outage is logged when it starts and when it ends, not once a second
        while not self._stop.is_set():
            try:
                if pubsub is None:
                    pubsub = self._redis.pubsub(ignore_subscribe_messages=True)
                    pubsub.subscribe(self._keys.map_events)
                    last_full = 0.0  # events may have been missed while unsubscribed
                message = pubsub.get_message(timeout=0.25)
                now = time.monotonic()
                if message is not None or now - last_full >= self._interval_s:
                    # drain a burst of events into one pass
                    while message is not None:
                        message = pubsub.get_message(timeout=0.0)
                    self.reconcile()
                    last_full = now
                if down:
                    logger.info("map sync: Redis reachable again")
                    down = False
            except redis.RedisError as exc:
                if not down:
                    logger.warning("map sync: Redis unavailable (%s); re-reading the shared maps folder every "
                                   "second until it is back", exc)
                    down = True
                if pubsub is not None:
                    try:
                        pubsub.close()
                    except redis.RedisError:
                        pass
                pubsub = None
                self._stop.wait(1.0)
                try:
                    self.reconcile()  # the shared folder still works without Redis
                except redis.RedisError:
                    pass  # the folder part ran; the build records wait for Redis (logged above)
                except Exception:  # noqa: BLE001 - never let the sync thread die
                    logger.exception("map sync pass failed")
            except Exception:  # noqa: BLE001 - never let the sync thread die
                logger.exception("map sync pass failed")
                self._stop.wait(1.0)
        if pubsub is not None:
            try:
                pubsub.close()
            except redis.RedisError:
                pass

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


def _valid_id(registry: MapRegistry, map_id: str) -> bool:
    try:
        registry.validate_id(map_id)
    except ServiceError:
        return False
    return True


# ---- everything together, per process -------------------------------------------------------------------------
class OpsRuntime:
    """The shared-state side of one service process: Redis client (or none), scan store, recent
    localizations, map sync and (with Redis) the build queue. Created in the app's lifespan."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.keys = Keys(settings.redis_namespace)
        self.origin = replica_id()
        self.redis: redis.Redis | None = connect(settings.redis_url) if settings.redis_url else None
        self.recent = RecentLocalizations(settings.recent_localizations, self.redis, self.keys)
        self.sync: MapSync | None = None
        self.folder_sync: FolderSync | None = None
        self.jobs: Any = None  # service.core.jobs.BuildQueue with Redis

    def scan_store(self) -> ScanCache:
        s = self.settings
        if self.redis is None:
            return ScanCache(s.scan_cache_size, s.scan_cache_ttl_s)
        return RedisScanStore(self.redis, self.keys, s.scan_cache_ttl_s)

    def session_store(self) -> SessionStore:
        """Tracking sessions: in this process, or with Redis in Redis (shared by every worker and replica)."""
        s = self.settings
        config = SessionConfig(max_sessions=s.max_sessions, ttl_s=s.session_ttl_s)
        if self.redis is None:
            return SessionStore(config)
        return RedisSessionStore(self.redis, self.keys, config)

    def make_registry(self, extractor: Any) -> MapRegistry:
        """A plain registry in one process; with Redis, one whose archive builds go to the job queue."""
        if self.redis is None:
            return MapRegistry(self.settings, extractor)
        from service.core.jobs import BuildQueue, QueuedMapRegistry

        self.jobs = BuildQueue(self.redis, self.keys, self.settings)
        return QueuedMapRegistry(self.settings, extractor, self.jobs, publish=self.publish)

    def publish(self, op: str, map_id: str) -> None:
        if self.sync is not None:
            self.sync.publish(op, map_id)

    def start(self, registry: MapRegistry) -> None:
        """Start following other replicas' map changes (with Redis), or the maps folder's (one process)."""
        if self.redis is None:
            self.folder_sync = FolderSync(registry, self.settings.map_sync_interval_s)
            self.folder_sync.start()
            return
        extra = None
        if self.jobs is not None and hasattr(registry, "reconcile_builds"):
            extra = registry.reconcile_builds
        self.sync = MapSync(self.redis, self.keys, registry, self.settings.map_sync_interval_s, self.origin,
                            extra_reconcile=extra)
        self.sync.start()

    def close(self) -> None:
        if self.folder_sync is not None:
            self.folder_sync.stop()
        if self.sync is not None:
            self.sync.stop()
        if self.redis is not None:
            self.redis.close()
