"""Service settings from environment variables (prefix ``RERADAR_``), documented in ``docs/SERVICE.md``."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import re
import secrets
import types
import typing
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from reradar_core.localization.pipeline import LocalizationConfig
from service.core.ids import MAP_ID_PATTERN

__all__ = ["Settings", "DEV_API_KEY", "MAP_ID_PATTERN", "MIN_KEY_LENGTH", "OPERATOR_KEY_FILE",
           "resolve_operator_key", "is_loopback"]

logger = logging.getLogger("service")

#: The key earlier versions documented as the development default. Published, hence refused everywhere.
DEV_API_KEY = "reradar-dev-key"

#: ``LocalizationConfig`` fields that were flat ``RERADAR_<FIELD>`` settings before they were nested.
_RENAMED_LOCALIZATION_FIELDS = ("TOP_K", "VERIFY_K", "MAX_CANDIDATES", "EXPAND_BELOW_SCREEN_SCORE", "MIN_INLIERS")

#: ``RERADAR_*`` variables that are not ``Settings`` fields but are read elsewhere (the library's cache, JIT
#: switch, network runtime and trajectory folder, ``reradar serve --workers``, scripts/setup.sh,
#: docker/compose.yaml, the vehicle client, a UI test): not reported as unknown settings.
OTHER_VARIABLES = frozenset({"CACHE_DIR", "JIT", "NETWORK_RUNTIME", "TRAJECTORY_DIR", "WORKERS", "VENV", "PYTHON",
                             "CLIENT_API_KEY", "REDIS_MAXMEMORY", "API_REPLICAS", "API_WORKERS", "BIND", "PORT",
                             "UI_SCREENSHOT"})


def _nested_names(config: type, prefix: str) -> set[str]:
    """Environment names of a dataclass config's fields, nested ones joined with ``__`` (upper case)."""
    import dataclasses
    import typing

    hints = typing.get_type_hints(config)  # the modules use postponed annotations: resolve the strings
    names = set()
    for f in dataclasses.fields(config):
        name = f"{prefix}{f.name.upper()}"
        names.add(name)
        if isinstance(hints.get(f.name), type) and dataclasses.is_dataclass(hints[f.name]):
            names |= _nested_names(hints[f.name], f"{name}__")
    return names


def unknown_json_keys(value: object, config: type, prefix: str = "") -> list[tuple[str, str | None]]:
    """Keys of ``value`` (the JSON form of a dataclass setting, e.g. ``RERADAR_LOCALIZATION='{"top_k": 3}'``) that
    are no field of ``config`` (nested dataclasses followed), each with the closest field name (None: nothing
    close). A JSON value that is not an object is left to the validation."""
    import dataclasses
    import difflib
    import typing

    if not isinstance(value, dict):
        return []
    hints = typing.get_type_hints(config)
    names = [f.name for f in dataclasses.fields(config)]
    out: list[tuple[str, str | None]] = []
    for key, item in value.items():
        if key not in names:
            close = difflib.get_close_matches(str(key), names, n=1, cutoff=0.6)
            out.append((f"{prefix}{key}", f"{prefix}{close[0]}" if close else None))
        elif isinstance(hints.get(key), type) and dataclasses.is_dataclass(hints[key]):
            out += unknown_json_keys(item, hints[key], f"{prefix}{key}.")
    return out


def unknown_variables(environ: dict[str, str] | None = None) -> list[tuple[str, str | None]]:
    """``RERADAR_*`` variables in ``environ`` (default: the process's) that nothing reads, each with the closest
    known name (None: nothing close): a misspelt setting is otherwise ignored without a word."""
    import difflib

    environ = dict(os.environ if environ is None else environ)
    known = {f"RERADAR_{name}" for name in OTHER_VARIABLES}
    known |= {f"RERADAR_{name.upper()}" for name in Settings.model_fields}
    known |= _nested_names(LocalizationConfig, "RERADAR_LOCALIZATION__")
    stale = {f"RERADAR_{name}" for name in _RENAMED_LOCALIZATION_FIELDS}  # refused with their own message
    out = []
    for var in sorted(environ):
        if var.startswith("RERADAR_") and var.upper() not in known | stale:
            close = difflib.get_close_matches(var.upper(), sorted(known), n=1, cutoff=0.8)
            out.append((var, close[0] if close else None))
    return out


#: Shortest API key accepted (operator or vehicle).
MIN_KEY_LENGTH = 16

#: File in ``maps_dir`` holding the operator key generated on first start when none is configured.
OPERATOR_KEY_FILE = ".operator-key"


def _sequence_fields(value: object, config: type) -> object:
    """``value`` (the nested dict pydantic-settings builds from ``RERADAR_LOCALIZATION__*`` variables) with each text
    given for a tuple field of the dataclass ``config`` (e.g. ``MOTION__RADII_M``) read as a list: ``[3, 2, 1]``,
    ``(3, 2, 1)`` or ``3,2,1`` (pydantic-settings decodes JSON only for top-level fields; a nested tuple was refused
    as "Input should be a valid tuple" whatever was written); values apart by commas and / or blanks. Text that does
    not parse is left for pydantic's error."""
    if not isinstance(value, dict) or not dataclasses.is_dataclass(config):
        return value
    hints = typing.get_type_hints(config)
    out = dict(value)
    for name, given in value.items():
        hint = hints.get(name)
        options = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)
        nested = next((o for o in options if isinstance(o, type) and dataclasses.is_dataclass(o)), None)
        if nested is not None:
            out[name] = _sequence_fields(given, nested)
        elif isinstance(given, str) and any(typing.get_origin(o) in (tuple, list) for o in options):
            text = given.strip()
            if text[:1] + text[-1:] in ("()", "[]"):
                text = text[1:-1]
            if text.lower() in ("none", "null") and type(None) in options:
                continue
            # values apart by commas and / or blanks, a trailing comma allowed: "3,2,1", "3 2 1", "3, 2, 1,"
            text = re.sub(r"[\s,]+", ",", text.strip().strip(","))
            try:
                out[name] = json.loads(f"[{text}]")
            except ValueError:
                pass
    return out


def is_loopback(host: str | None) -> bool:
    """True for 127.0.0.0/8, ::1, ``localhost`` (and IPv4-mapped loopback)."""
    import ipaddress

    if not host:
        return False
    if host == "localhost":
        return True
    try:
        addr = ipaddress.ip_address(host.split("%", 1)[0])
    except ValueError:
        return False
    if isinstance(addr, ipaddress.IPv6Address) and addr.ipv4_mapped is not None:
        addr = addr.ipv4_mapped
    return addr.is_loopback


def _default_maps_dir() -> Path:
    return Path(os.environ.get("RERADAR_CACHE_DIR", Path.cwd() / ".cache" / "reradar")) / "maps"


def redis_url_parts(url: str) -> dict[str, Any]:
    """The connection settings of ``url`` (``redis://[[user]:password@]host[:port][/db]``, ``rediss://`` for TLS,
    ``unix://[[user]:password@]/absolute/socket/path[?db=N]``) as redis-py reads them (a percent-encoded password
    decoded), after checking what redis-py would silently ignore: a path other than a database number (``/0/``,
    ``/abc``), a host in a unix:// URL (``unix://tmp/redis.sock`` is the socket ``/redis.sock``), or no socket path.

    Raises:
        ValueError: a malformed URL, naming the part (never the password).
    """
    from urllib.parse import urlsplit

    from redis.connection import parse_url

    try:
        parts = dict(parse_url(url))
        path = urlsplit(url).path
    except ValueError as exc:
        raise ValueError(f"not a Redis URL ({exc}); e.g. redis://redis:6379/0") from None
    if url.startswith("unix://"):
        host = urlsplit(url).netloc.rpartition("@")[2]
        if host:
            raise ValueError(f"a unix:// URL names the socket by its absolute path after three slashes, e.g. "
                             f"unix:///run/redis/redis.sock; {host!r} before the path would be ignored")
        if path in ("", "/"):
            raise ValueError("the unix:// URL names no socket file; e.g. unix:///run/redis/redis.sock")
    elif path not in ("", "/") and not re.fullmatch(r"/\d+", path):
        raise ValueError(f"the path {path!r} is not a database number (e.g. "
                          "redis://redis:6379/0)")
    return parts


class Settings(BaseSettings):
    """Service configuration. Every field can be set as ``RERADAR_<FIELD>`` (e.g. ``RERADAR_API_KEY``)."""

    model_config = SettingsConfigDict(env_prefix="RERADAR_", extra="ignore", env_nested_delimiter="__",
                                      env_parse_none_str="none")  # "none" sets an optional field to None

    environment: Literal["development", "production"] = Field(
        default="development", description=(
            "`production` requires both keys to be configured (no generated operator key, no anonymous vehicles "
            "on loopback)."))
    api_key: SecretStr | None = Field(default=None, description=(
        "Operator key (X-API-Key header) for registering and deleting maps; also accepted where a vehicle key "
        "is. Unset: a random key is generated on first start, stored in `<maps_dir>/.operator-key` (mode 0600) "
        "and printed once in the log."))
    vehicle_keys: SecretStr | None = Field(default=None, description=(
        "Comma-separated vehicle keys (X-API-Key header) for POST /scans, /localize and /maps/{id}/retrieve. "
        "Unset: those endpoints answer only clients on the loopback interface (local development)."))
    model: str = Field(default="default",
                       description="Descriptor model: registry name (`default` = shipped default) or a .pt path.")
    maps_dir: Path = Field(default_factory=_default_maps_dir,
                           description="Folder holding the registered maps (<map_id>.h5).")
    load_demo_map: bool = Field(default=True, description=(
        "Copy the shipped demo map into maps_dir as map `demo` (not after DELETE /maps/demo: .demo-deleted)."))
    max_upload_mb: float = Field(default=8.0, gt=0, description=(
        "Largest scan upload / request body, MB: a Navtech PNG is ~0.5 MB (its raw .npy 1.3 MB), a float32 .npy of the largest "
        "accepted scan 6.4 MB. The guard holds a scan request's body in memory, so this bounds what a junk body "
        "costs (measured in docs/SERVICE.md); send float64 arrays as float32 or uint8."))
    max_map_upload_mb: float = Field(default=512.0, gt=0, description="Largest map or scan-archive upload, MB.")
    max_archive_scans: int = Field(default=20_000, gt=0, description="Most scans accepted in one scan archive.")
    max_pose_file_mb: float = Field(default=128.0, gt=0, description=(
        "Largest pose file sent with a scan archive, MB (a Boreas radar_poses.csv is ~0.15 MB per hour of driving, "
        "a 100 Hz pose log ~70 MB; reading one keeps ~3 times its size at the peak, docs/SERVICE.md)."))
    scan_cache_size: int = Field(default=256, gt=0, description="Uploaded scans whose features are kept.")
    scan_cache_ttl_s: float = Field(default=600.0, gt=0, description="Seconds an uploaded scan's features are kept.")
    localization: LocalizationConfig = Field(default_factory=LocalizationConfig, description=(
        "Localization settings (`reradar_core.localization.LocalizationConfig`, defaults documented there); "
        "each field is `RERADAR_LOCALIZATION__<FIELD>`, nested ones e.g. "
        "`RERADAR_LOCALIZATION__ALIGNMENT__SCREEN_HYPOTHESES`. `top_k` is also the default of `retrieve`."))
    keyframe_cache_size: int = Field(default=1000, ge=1, description=(
        "Keyframes per map whose features and compact screen data (bit-packed alignment mask; ~50 KB each "
        "with 512 landmarks, measured) stay in memory (LRU). A cold keyframe costs ~1.3 ms to read and grid, "
        "as much as screening it, so maps up to this size are held whole; 1000 keeps a 100,000-keyframe map "
        "at ~0.5 KB per keyframe of cache on top of the index."))
    far_view: bool = Field(default=True, description=(
        "Serve a map's far-view companion (`<map>.far.h5`, written by `reradar build-map --far-view`) for the "
        "answers its own view refuses: the same network on the radar's whole range (docs/MODEL.md, 'The far view'). "
        "Maps without one are served as before; `false` ignores every companion."))
    preload_keyframes: bool = Field(default=True, description=(
        "Read every keyframe when a map that fits in `keyframe_cache_size` is loaded, so no query pays for "
        "cold reads (560 keyframes: ~1 s at start-up, ~28 MB)."))
    share_map_arrays: bool = Field(default=True, description=(
        "Serve each map's keyframe features and screen masks from one memory-mapped arrays file per map version "
        "(`maps.arrays`, in `map_arrays_dir`; written by the first process that loads the map, atomically, "
        "verified by every process that opens it), so every worker process shares those pages instead of "
        "holding a private copy. False: each process reads the keyframes from the HDF5 map into its own memory."))
    map_arrays_dir: Path | None = Field(default=None, description=(
        "Folder of the shared map arrays files; default `<maps_dir>/.arrays`. Local disk: every process that "
        "serves a map maps this file."))
    session_ttl_s: float = Field(default=60.0, gt=0, description=(
        "Seconds a tracking session's last pose is kept without a new scan (then the next scan is global)."))
    max_sessions: int = Field(default=10_000, ge=1, description="Tracking sessions kept (least recently used dropped).")
    index_kind: Literal["auto", "flat", "hnsw", "ivf"] = Field(default="auto", description="FAISS index type.")
    index_exact_max_size: int = Field(default=20_000, ge=0, description="`auto` uses exact search up to this size.")
    torch_threads: int = Field(default=1, ge=1, description=(
        "torch CPU threads for feature extraction. 1 by default: one request at a time gains little from "
        "intra-op threads on 2 cores, and OpenMP workers spin-waiting between requests starve the rest of the "
        "pipeline (measured: network 28 ms with 1 thread vs 0.3-1.9 s with 2 on the loaded 2-core box)."))
    blas_threads: int = Field(default=1, ge=1, description="OpenBLAS threads of numpy, scipy and opencv (1: small products stay fast).")
    malloc_arenas: int = Field(default=2, ge=0, description=(
        "glibc malloc arenas of each service process (`MALLOC_ARENA_MAX`), set at start-up: with 2 a 2-worker "
        "service's private memory stayed 40-60 MB lower under sustained load than with glibc's default (8 per "
        "core), at the same throughput; 0 = leave glibc's default."))
    build_batch_size: int = Field(default=8, ge=1, description="Scans per network batch when building maps.")
    max_scan_pixels: int = Field(default=1_600_000, ge=4096, description=(
        "Largest scan accepted, in pixels (azimuths x columns), read from the PNG / .npy header before "
        "decoding: 6 % above an Oxford sweep (400 x 3,779 PNG pixels), so no request costs much more memory "
        "than a normal one (measured in docs/SERVICE.md); raise it for sensors with more range bins."))
    max_concurrent_requests: int = Field(default=4, ge=1, description=(
        "Scan and map requests (POST /scans, /localize, /maps/{id}/retrieve, /maps) in progress at once; "
        "more are answered 503 with Retry-After at once instead of queueing."))
    max_concurrent_per_key: int = Field(default=2, ge=1, description=(
        "Of those, the most one API key may have in progress at once; more are answered 429 with Retry-After: a "
        "client trickling request bodies (or a leaked key) cannot take every slot and lock the other vehicles "
        "out. Keyless loopback clients (a local setup without vehicle keys) are not limited."))
    retry_after_s: int = Field(default=1, ge=1, description="Retry-After seconds sent with 503 overloaded and 429.")
    body_idle_timeout_s: float = Field(default=10.0, gt=0, description=(
        "A request body that sends nothing for this long is refused with 408 (slow-client protection)."))
    body_timeout_s: float = Field(default=30.0, gt=0, description=(
        "Longest time to receive a whole scan request body, seconds (408 after)."))
    header_timeout_s: float = Field(default=10.0, gt=0, description=(
        "A connection whose request line and headers are not complete this long after it opened (or after its "
        "previous response) is closed (`reradar serve`; slow-client protection before a request exists)."))
    body_min_rate_kib_s: float = Field(default=32.0, ge=0, description=(
        "Slowest average rate of a request body, KiB/s, checked from 5 s after its start (408 below): a client "
        "trickling a body holds one of the max_concurrent_requests slots (a 1.3 MB raw .npy scan at 32 KiB/s takes "
        "40 s, over body_timeout_s anyway); 0 = no minimum."))
    map_upload_timeout_s: float = Field(default=900.0, gt=0, description=(
        "Longest time to receive a whole POST /maps body, seconds (408 after)."))
    # ---- operations (docs/OPERATIONS.md) ---------------------------------------------------------------
    log_format: Literal["json", "text"] = Field(default="json", description=(
        "Log line format of the service and worker: `json` (one JSON object per line) or `text`."))
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field(default="INFO", description="Log level.")
    redis_url: str | None = Field(default=None, description=(
        "Redis shared by every replica (e.g. `redis://redis:6379/0`; `rediss://` for TLS, "
        "`unix:///run/redis/redis.sock?db=0` for a socket on the host): uploaded scans, map registry events, "
        "recent localizations and the map build queue. Unset = one process keeps all of it in memory."))
    redis_namespace: str = Field(default="reradar", pattern=r"^[a-z0-9_-]{1,32}$", description=(
        "Prefix of every Redis key (`<namespace>:v1:...`), so several deployments can share one Redis."))
    map_sync_interval_s: float = Field(default=5.0, gt=0, description=(
        "With Redis, every replica re-checks the shared maps folder this often in case a registry event "
        "was missed (events themselves apply within a second); in one process without Redis, the maps folder is "
        "re-read this often, so a map file copied in, removed or rebuilt in place by hand is served, dropped or "
        "reopened within this time."))
    recent_localizations: int = Field(default=200, ge=1, le=10_000, description=(
        "Latest localizations per map kept for the operator page."))
    build_job_timeout_s: float = Field(default=3600.0, gt=0, description=(
        "Longest a queued map build may run before the worker gives up on it."))
    build_heartbeat_stale_s: float = Field(default=15.0, gt=0, description=(
        "A running build whose worker sent no heartbeat for this long is taken as crashed and retried."))
    build_max_tries: int = Field(default=3, ge=1, description="Attempts of a queued map build before it fails.")

    @model_validator(mode="after")
    def _refuse_renamed_localization_variables(self) -> Settings:
        # the localization fields used to be flat settings; a stale variable would otherwise be ignored silently
        stale = [f"RERADAR_{name}" for name in _RENAMED_LOCALIZATION_FIELDS if f"RERADAR_{name}" in os.environ]
        if stale:
            raise ValueError(", ".join(f"{v} is now RERADAR_LOCALIZATION__{v.removeprefix('RERADAR_')}"
                                       for v in stale))
        # the descriptor network's runtime is read by the extractor at start-up: a typo is a setting error (exit 2),
        # not a traceback when the app's lifespan loads the model
        from reradar_core.errors import ConfigError
        from reradar_core.model.runtime import resolve_runtime

        try:
            resolve_runtime(None)
        except ConfigError as exc:
            raise ValueError(str(exc)) from None
        # the JSON form of the same settings (RERADAR_LOCALIZATION='{"top_k": 3}') ignores unknown keys too
        raw = next((v for k, v in os.environ.items() if k.upper() == "RERADAR_LOCALIZATION"), None)
        if raw:
            import json

            try:
                keys = unknown_json_keys(json.loads(raw), LocalizationConfig)
            except ValueError:  # not JSON: the field's own validation says so
                keys = []
            if keys:
                raise ValueError("; ".join(f"RERADAR_LOCALIZATION: {k!r} is no localization setting" + (
                    f" (did you mean {near!r}?)" if near else "") for k, near in keys))
        # a misspelt localization field is a setting that silently does nothing: nothing else reads that prefix
        typos = [(v, near) for v, near in unknown_variables() if v.upper().startswith("RERADAR_LOCALIZATION__")]
        if typos:
            raise ValueError("; ".join(f"{v} is no localization setting" + (f" (did you mean {near}?)" if near else
                                       " (docs/SERVICE.md lists them)") for v, near in typos))
        return self

    @field_validator("localization", mode="before")
    @classmethod
    def _sequences_from_text(cls, value: object) -> object:
        return _sequence_fields(value, LocalizationConfig)

    @field_validator("redis_url")
    @classmethod
    def _redis_url_is_one_both_clients_read(cls, value: str | None) -> str | None:
        if value:  # the service's client and the build queue's must read it alike (``redis_url_parts``)
            redis_url_parts(value)
        return value or None

    @field_validator("maps_dir")
    @classmethod
    def _maps_dir_is_a_folder(cls, value: Path) -> Path:
        # one line at start-up (serve and worker) rather than a traceback when the first map is read
        if value.exists() and not value.is_dir():
            raise ValueError(f"the maps folder {value} is a file; give a folder (--maps-dir or RERADAR_MAPS_DIR)")
        return value

    @field_validator("log_level", mode="before")
    @classmethod
    def _log_level_in_any_case(cls, value: object) -> object:
        # `reradar serve --log-level` takes lower case: the variable takes its four levels in any case too
        return value.strip().upper() if isinstance(value, str) else value

    @field_validator("api_key", "vehicle_keys", mode="before")
    @classmethod
    def _empty_is_unset(cls, value: object) -> object:
        # compose passes unset variables as empty strings
        if isinstance(value, str) and not value.strip():
            return None
        return value

    @model_validator(mode="after")
    def _refuse_unsafe_keys(self) -> Settings:
        keys = {"RERADAR_API_KEY": [self.api_key.get_secret_value()] if self.api_key else [],
                "RERADAR_VEHICLE_KEYS": self.vehicle_key_list}
        for env, values in keys.items():
            for key in values:
                if key == DEV_API_KEY:
                    raise ValueError(f"{env}: the published development key {DEV_API_KEY!r} is refused; "
                                     f"set a secret (e.g. python -c 'import secrets; print(secrets.token_urlsafe(24))')")
                if len(key) < MIN_KEY_LENGTH:
                    raise ValueError(f"{env}: keys must be at least {MIN_KEY_LENGTH} characters")
        if self.environment == "production" and (self.api_key is None or not self.vehicle_key_list):
            raise ValueError("RERADAR_ENVIRONMENT=production needs RERADAR_API_KEY (operator) and "
                             "RERADAR_VEHICLE_KEYS (comma-separated) set to secrets of at least "
                             f"{MIN_KEY_LENGTH} characters")
        return self

    @property
    def vehicle_key_list(self) -> list[str]:
        """The configured vehicle keys (empty when none)."""
        if self.vehicle_keys is None:
            return []
        return [k.strip() for k in self.vehicle_keys.get_secret_value().split(",") if k.strip()]

    @property
    def arrays_dir(self) -> Path | None:
        """Where the shared map arrays live (None when ``share_map_arrays`` is off)."""
        if not self.share_map_arrays:
            return None
        return Path(self.map_arrays_dir) if self.map_arrays_dir is not None else Path(self.maps_dir) / ".arrays"

    @property
    def max_upload_bytes(self) -> int:
        return int(self.max_upload_mb * 1024 * 1024)

    @property
    def max_map_upload_bytes(self) -> int:
        return int(self.max_map_upload_mb * 1024 * 1024)

    @property
    def max_pose_file_bytes(self) -> int:
        return int(self.max_pose_file_mb * 1024 * 1024)


def resolve_operator_key(settings: Settings) -> str:
    """The operator key: ``settings.api_key`` when configured; otherwise the key stored in
    ``<maps_dir>/.operator-key``, generated (and printed once in the log) on first start.

    The generated key is written atomically (temporary file, fsync, rename) with mode 0600, so that a restart
    or a second replica on the same maps folder uses the same key, and no published default ever works.
    """
    if settings.api_key is not None:
        return settings.api_key.get_secret_value()
    maps_dir = Path(settings.maps_dir)
    maps_dir.mkdir(parents=True, exist_ok=True)
    path = maps_dir / OPERATOR_KEY_FILE
    if path.is_file():
        key = path.read_text().strip()
        if len(key) >= MIN_KEY_LENGTH:
            logger.info("operator key: the generated key stored in %s (set RERADAR_API_KEY to choose one)",
                        OPERATOR_KEY_FILE)
            return key
        path.unlink()  # emptied or edited by hand: replace it
    key = secrets.token_urlsafe(24)
    tmp = maps_dir / f".{OPERATOR_KEY_FILE}.{os.getpid()}.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.write(fd, (key + "\n").encode())
        os.fsync(fd)
    finally:
        os.close(fd)
    try:
        os.link(tmp, path)  # fails when another process created the key first: then use that one
    except FileExistsError:
        key = path.read_text().strip()
        return key
    finally:
        os.unlink(tmp)
    logger.warning("no RERADAR_API_KEY configured: generated the operator key %s (stored in %s in the maps "
                   "folder; shown only this once). Send it as X-API-Key to register or delete maps.",
                   key, OPERATOR_KEY_FILE)
    return key
