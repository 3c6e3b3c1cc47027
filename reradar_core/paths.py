"""Where generated data goes: an ignored cache folder, never the repository's tracked tree."""

from __future__ import annotations

import os
from pathlib import Path

from reradar_core.errors import ConfigError

__all__ = ["cache_dir", "PACKAGE_DIR", "CACHE_SOURCE_FILE", "CACHE_SOURCE_ATTR"]

PACKAGE_DIR = Path(__file__).resolve().parent
#: A cache folder derived from one input folder names it in this JSON file (``{"root": ...}``), and an HDF5 cache
#: file in this attribute, so that ``reradar cache --prune`` can drop what was derived from folders that are gone.
CACHE_SOURCE_FILE = "source.json"
CACHE_SOURCE_ATTR = "source_root"


def cache_dir(*parts: str) -> Path:
    """``$RERADAR_CACHE_DIR`` (default ``./.cache/reradar``) joined with ``parts``; created on demand.

    Raises:
        ConfigError: the folder cannot be created (``RERADAR_CACHE_DIR`` names a file, or no permission).
    """
    root = Path(os.environ.get("RERADAR_CACHE_DIR", Path.cwd() / ".cache" / "reradar"))
    path = root.joinpath(*parts)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        why = ("it (or a folder on its path) is a file, not a folder"
               if isinstance(exc, (FileExistsError, NotADirectoryError)) else (exc.strerror or str(exc)))
        raise ConfigError(f"RERADAR_CACHE_DIR={os.environ.get('RERADAR_CACHE_DIR', '')} cannot be used as the "
                          f"cache folder: {why}") from None
    return path
