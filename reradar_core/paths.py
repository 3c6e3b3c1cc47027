"""Where generated data goes: an ignored cache folder, never the repository's tracked tree."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["cache_dir", "PACKAGE_DIR", "CACHE_SOURCE_FILE", "CACHE_SOURCE_ATTR"]

PACKAGE_DIR = Path(__file__).resolve().parent
#: A cache folder derived from one input folder names it in this JSON file (``{"root": ...}``), and an HDF5 cache
#: file in this attribute, so that ``reradar cache --prune`` can drop what was derived from folders that are gone.
CACHE_SOURCE_FILE = "source.json"
CACHE_SOURCE_ATTR = "source_root"


def cache_dir(*parts: str) -> Path:
    """``$RERADAR_CACHE_DIR`` (default ``./.cache/reradar``) joined with ``parts``; created on demand."""
    root = Path(os.environ.get("RERADAR_CACHE_DIR", Path.cwd() / ".cache" / "reradar"))
    path = root.joinpath(*parts)
    path.mkdir(parents=True, exist_ok=True)
    return path
