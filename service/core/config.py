"""Service settings from environment variables (prefix ``RERADAR_``), documented in ``docs/SERVICE.md``."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from reradar_core.localization.pipeline import LocalizationConfig
from service.core.ids import MAP_ID_PATTERN

__all__ = ["Settings", "DEV_API_KEY", "MAP_ID_PATTERN"]

#: API key accepted in ``development`` when none is configured; refused in ``production``.
DEV_API_KEY = "reradar-dev-key"



#: ``LocalizationConfig`` fields that were flat ``RERADAR_<FIELD>`` settings before they were nested.
_RENAMED_LOCALIZATION_FIELDS = ("TOP_K", "VERIFY_K", "MAX_CANDIDATES", "EXPAND_BELOW_SCREEN_SCORE", "MIN_INLIERS")


def _default_maps_dir() -> Path:
    return Path(os.environ.get("RERADAR_CACHE_DIR", Path.cwd() / ".cache" / "reradar")) / "maps"


class Settings(BaseSettings):
    """Service configuration. Every field can be set as ``RERADAR_<FIELD>`` (e.g. ``RERADAR_API_KEY``)."""

    model_config = SettingsConfigDict(env_prefix="RERADAR_", extra="ignore", env_nested_delimiter="__")

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
    localization: LocalizationConfig = Field(default_factory=LocalizationConfig, description=(
        "Localization settings (`reradar_core.localization.LocalizationConfig`, defaults documented there); "
        "each field is `RERADAR_LOCALIZATION__<FIELD>`, nested ones e.g. "
        "`RERADAR_LOCALIZATION__ALIGNMENT__SCREEN_HYPOTHESES`. `top_k` is also the default of `retrieve`."))
    keyframe_cache_size: int = Field(default=1000, ge=1, description=(
        "Keyframes per map whose features and compact screen data (bit-packed alignment mask; ~50 KB each "
        "with 512 landmarks, measured) stay in memory (LRU). A cold keyframe costs ~1.3 ms to read and grid, "
        "as much as screening it, so maps up to this size are held whole; 1000 keeps a 100,000-keyframe map "
        "at ~0.5 KB per keyframe of cache on top of the index."))
    preload_keyframes: bool = Field(default=True, description=(
        "Read every keyframe when a map that fits in `keyframe_cache_size` is loaded, so no query pays for "
        "cold reads (560 keyframes: ~1 s at start-up, ~28 MB)."))
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
    build_batch_size: int = Field(default=8, ge=1, description="Scans per network batch when building maps.")

    @model_validator(mode="after")
    def _refuse_renamed_localization_variables(self) -> Settings:
        # the localization fields used to be flat settings; a stale variable would otherwise be ignored silently
        stale = [f"RERADAR_{name}" for name in _RENAMED_LOCALIZATION_FIELDS if f"RERADAR_{name}" in os.environ]
        if stale:
            raise ValueError(", ".join(f"{v} is now RERADAR_LOCALIZATION__{v.removeprefix('RERADAR_')}"
                                       for v in stale))
        return self

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
