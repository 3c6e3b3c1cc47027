"""Where generated data goes: an ignored cache folder, never the repository's tracked tree."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from reradar_core.errors import ConfigError

__all__ = ["cache_dir", "output_dir", "output_file", "distinct_folder_labels", "PACKAGE_DIR", "CACHE_SOURCE_FILE",
           "CACHE_SOURCE_ATTR"]

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
    # an empty value (``RERADAR_CACHE_DIR=`` in an .env file) is unset, not the current folder
    root = Path(os.environ.get("RERADAR_CACHE_DIR") or Path.cwd() / ".cache" / "reradar")
    path = root.joinpath(*parts)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        why = ("it (or a folder on its path) is a file, not a folder"
               if isinstance(exc, (FileExistsError, NotADirectoryError)) else (exc.strerror or str(exc)))
        raise ConfigError(f"RERADAR_CACHE_DIR={os.environ.get('RERADAR_CACHE_DIR', '')} cannot be used as the "
                          f"cache folder: {why}") from None
    return path


def _why(exc: OSError) -> str:
    if isinstance(exc, (FileExistsError, NotADirectoryError)):
        return "a file is in the way (it, or a folder on its path, is a file)"
    return exc.strerror or str(exc)


def output_dir(path: str | Path, what: str = "--out", create: bool = True) -> Path:
    """Create the output folder ``path`` (with its parents) before any work is done, so that a long run cannot end
    in a failed write; with ``create=False`` only check that it could be (a run refused later for another reason
    then leaves no empty folder behind).

    Raises:
        ConfigError: naming ``what`` (the option) and the reason: a file in the way, no permission, ...
    """
    path = Path(path)
    if not create:
        existing = next((p for p in (path, *path.parents) if p.exists()), Path("."))
        if not existing.is_dir():
            raise ConfigError(f"{what} {path}: cannot create the folder: a file is in the way ({existing.name} is a "
                              "file)")
        if not os.access(existing, os.W_OK | os.X_OK):
            raise ConfigError(f"{what} {path}: cannot create the folder: {existing} is not writable")
        try:  # access() says yes to root on /proc, /sys and the like: a folder made and removed at once settles it
            os.rmdir(tempfile.mkdtemp(prefix=".reradar-probe-", dir=existing))
        except OSError as exc:
            raise ConfigError(f"{what} {path}: cannot create the folder: {_why(exc)}") from None
        return path
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"{what} {path}: cannot create the folder: {_why(exc)}") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise ConfigError(f"{what} {path}: the folder is not writable")
    return path


def output_file(path: str | Path, what: str = "--out", suffixes: tuple[str, ...] = ()) -> Path:
    """Check, before any work is done, that the output file ``path`` can be written: not a folder, a suffix from
    ``suffixes`` (when given), its parent folder created and writable.

    Raises:
        ConfigError: naming ``what`` and the reason.
    """
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{what} {path}: is a folder; give a file name"
                          + (f" ending in {' or '.join(suffixes)}" if suffixes else ""))
    if suffixes and path.suffix.lower() not in suffixes:
        raise ConfigError(f"{what} {path}: the file name must end in {' or '.join(suffixes)}")
    output_dir(path.parent, what)
    return path



def distinct_folder_labels(folders: list[Path], sep: str = "/") -> list[str]:
    """A label per folder: its name, or, where several folders share a name (``a/seq`` and ``b/seq``), its parent
    folders' names joined with ``sep`` as far up as it takes to tell them apart (``a/seq``, ``b/seq``); the same
    folder twice gets one label twice (its whole path without the root). Folders are compared resolved (links and ``..`` followed)."""
    parts = [Path(f).resolve().parts[1:] or (Path(f).resolve().name,) for f in folders]  # without the root "/"
    labels = [p[-1] for p in parts]
    for depth in range(2, max((len(p) for p in parts), default=1) + 1):
        clash = {lab for lab in labels if labels.count(lab) > 1}
        if not clash:
            break
        labels = [sep.join(p[-depth:]) if lab in clash else lab for lab, p in zip(labels, parts, strict=True)]
    return labels
