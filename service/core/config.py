"""Service settings from environment variables (prefix ``RERADAR_``), documented in ``docs/SERVICE.md``."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

__all__ = ["Settings", "DEV_API_KEY", "MAP_ID_PATTERN"]

#: API key accepted in ``development`` when none is configured; refused in ``production``.
DEV_API_KEY = "reradar-dev-key"

#: Map ids: lower-case letters, digits, ``_`` and ``-``; no dots or slashes, so an id can never escape
#: the maps directory.
MAP_ID_PATTERN = r"^[a-z0-9][a-z0-9_-]{0,63}$"


def _default_maps_dir() -> Path:
    return Path(os.environ.get("RERADAR_CACHE_DIR", Path.cwd() / ".cache" / "reradar")) / "maps"


class Settings(BaseSettings):
    """Service configuration. Every field can be set as ``RERADAR_<FIELD>`` (e.g. ``RERADAR_API_KEY``)."""

    model_config = SettingsConfigDict(env_prefix="RERADAR_", extra="ignore")

    environment: Literal["development", "production"] = Field(
        default="development", description="`production` refuses the development API key.")
    api_key: SecretStr = Field(default=SecretStr(DEV_API_KEY),
                               description="Key required in the X-API-Key header of mutating endpoints.")
    model: str = Field(default="default",
                       description="Descriptor model: registry name (`default` = shipped default) or a .pt path.")
    maps_dir: Path = Field(default_factory=_default_maps_dir,
                           description="Folder holding the registered maps (<map_id>.h5).")
    load_demo_map: bool = Field(default=True, description="Copy the shipped demo map into maps_dir as map `demo`.")
    max_upload_mb: float = Field(default=20.0, gt=0, description="Largest scan upload / request body, MB.")
    max_map_upload_mb: float = Field(default=512.0, gt=0, description="Largest map or scan-archive upload, MB.")
    max_archive_scans: int = Field(default=20_000, gt=0, description="Most scans accepted in one scan archive.")
    scan_cache_size: int = Field(default=256, gt=0, description="Uploaded scans whose features are kept.")
    scan_cache_ttl_s: float = Field(default=600.0, gt=0, description="Seconds an uploaded scan's features are kept.")
    top_k: int = Field(default=20, ge=1, le=100, description=(
        "Default number of retrieved candidates; all are screened by landmark alignment and the best "
        "`verify_k` get the full pose estimate."))
    verify_k: int = Field(default=3, ge=1, le=100, description="Screened candidates verified in full.")
    max_candidates: int = Field(default=60, ge=1, le=500, description=(
        "When no screened candidate aligns `expand_below_screen_score` of the query's landmarks, the next "
        "`top_k` retrieved keyframes are screened too, up to this many."))
    expand_below_screen_score: float = Field(default=0.6, ge=0.0, le=1.0, description=(
        "Screen score (fraction of query landmarks aligned) under which screening continues."))
    keyframe_cache_size: int = Field(default=128, ge=1, description=(
        "Keyframes per map whose features and landmark grid stay in memory (LRU, ~0.33 MB each). A cold "
        "keyframe costs ~1.3 ms per candidate; maps queried all over benefit from a cache as large as the map."))
    min_inliers: int = Field(default=12, ge=2, description="Inliers (aligned query landmarks) needed to report `localized`; at least 50 % of the query's landmarks must align too.")
    index_kind: Literal["auto", "flat", "hnsw", "ivf"] = Field(default="auto", description="FAISS index type.")
    index_exact_max_size: int = Field(default=20_000, ge=0, description="`auto` uses exact search up to this size.")
    torch_threads: int = Field(default=1, ge=1, description=(
        "torch CPU threads for feature extraction. 1 by default: one request at a time gains little from "
        "intra-op threads on 2 cores, and OpenMP workers spin-waiting between requests starve the rest of the "
        "pipeline (measured: network 28 ms with 1 thread vs 0.3-1.9 s with 2 on the loaded 2-core box)."))
    blas_threads: int = Field(default=1, ge=1, description="OpenBLAS threads of numpy, scipy and opencv (1: small products stay fast).")
    build_batch_size: int = Field(default=8, ge=1, description="Scans per network batch when building maps.")
    # ---- operations (docs/OPERATIONS.md) ---------------------------------------------------------------
    log_format: Literal["json", "text"] = Field(default="json", description=(
        "Log line format of the service and worker: `json` (one JSON object per line) or `text`."))
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field(default="INFO", description="Log level.")
    redis_url: str | None = Field(default=None, description=(
        "Redis shared by every replica (e.g. `redis://redis:6379/0`): uploaded scans, map registry events, "
        "recent localizations and the map build queue. Unset = one process keeps all of it in memory."))
    redis_namespace: str = Field(default="reradar", pattern=r"^[a-z0-9_-]{1,32}$", description=(
        "Prefix of every Redis key (`<namespace>:v1:...`), so several deployments can share one Redis."))
    map_sync_interval_s: float = Field(default=5.0, gt=0, description=(
        "With Redis, every replica re-checks the shared maps folder this often in case a registry event "
        "was missed (events themselves apply within a second)."))
    recent_localizations: int = Field(default=200, ge=1, le=10_000, description=(
        "Latest localizations per map kept for the operator page."))
    build_job_timeout_s: float = Field(default=3600.0, gt=0, description=(
        "Longest a queued map build may run before the worker gives up on it."))
    build_heartbeat_stale_s: float = Field(default=15.0, gt=0, description=(
        "A running build whose worker sent no heartbeat for this long is taken as crashed and retried."))
    build_max_tries: int = Field(default=3, ge=1, description="Attempts of a queued map build before it fails.")

    @model_validator(mode="after")
    def _refuse_unsafe_defaults(self) -> Settings:
        key = self.api_key.get_secret_value()
        if self.environment == "production" and (key == DEV_API_KEY or len(key) < 16):
            raise ValueError(
                "RERADAR_API_KEY must be set to a secret of at least 16 characters when "
                "RERADAR_ENVIRONMENT=production (the development key is refused)"
            )
        return self

    @property
    def max_upload_bytes(self) -> int:
        return int(self.max_upload_mb * 1024 * 1024)

    @property
    def max_map_upload_bytes(self) -> int:
        return int(self.max_map_upload_mb * 1024 * 1024)
