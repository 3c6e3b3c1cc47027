"""On-disk feature cache: one HDF5 file per (method parameters, sequence), one group per scan.

As hloc's feature files: writers resume by skipping scans already stored, so a re-run only recomputes
scans whose file changed (size / mtime differ) or methods whose parameters changed (new cache key). Each
group also stores how long the computation took (``compute_ms``) so per-query timings survive re-runs.
All h5py access for the benchmark lives here.
"""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import h5py
import numpy as np

from reradar_core.baselines.base import Prepared
from reradar_core.errors import ReRadarError
from reradar_core.paths import CACHE_SOURCE_ATTR, cache_dir

__all__ = ["FeatureCache", "SCHEMA_VERSION", "sequence_key"]

logger = logging.getLogger(__name__)

SCHEMA_VERSION = 1


def sequence_key(name: str, root: str | Path, preset: str | None = None) -> str:
    """Cache-file stem for a sequence: its name plus a hash of its absolute folder and the radar preset it is read
    with (the same folder read as boreas or boreas-2021 has other ranges: QA session 38 got the other preset's
    figures from the cache)."""
    h = hashlib.sha256(f"{Path(root).resolve()}|{preset or ''}".encode()).hexdigest()[:8]
    return f"{name}-{h}"


def _stamp(path: Path) -> tuple[int, int]:
    st = path.stat()
    return int(st.st_size), int(st.st_mtime_ns)


class FeatureCache:
    """Prepared records of one method on one sequence (``<root>/<method_key>/<sequence_key>.h5``).

    Args:
        method_key: ``PlaceRecognitionMethod.cache_key``.
        seq_key: ``sequence_key(...)``.
        root: cache root; default ``cache_dir("bench", "features")``.
        enabled: False keeps everything in memory only (nothing written).
        source_root: the sequence folder, recorded in the file (attribute ``paths.CACHE_SOURCE_ATTR``) so that
            ``reradar cache`` can tell a cache whose sequence no longer exists.
    """

    def __init__(self, method_key: str, seq_key: str, root: Path | None = None, enabled: bool = True,
                 source_root: Path | None = None) -> None:
        self.enabled = enabled
        self.path = (root or cache_dir("bench", "features")) / method_key / f"{seq_key}.h5"
        self._file: h5py.File | None = None
        if enabled:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            try:
                self._file = h5py.File(self.path, "a")
            except BlockingIOError:  # another run holds the file: never touch it, compute in memory
                logger.warning("feature cache %s is in use by another run; not caching this time", self.path)
                self.enabled = False
                return
            except OSError as exc:  # corrupt file from an interrupted run: start over
                logger.warning("feature cache %s unreadable (%s); recreating it", self.path, exc)
                self.path.unlink(missing_ok=True)
                self._file = h5py.File(self.path, "a")
            version = int(self._file.attrs.get("schema_version", SCHEMA_VERSION))
            if version != SCHEMA_VERSION:
                raise ReRadarError(f"{self.path}: feature cache schema {version}, expected {SCHEMA_VERSION}; "
                                   "delete the file to rebuild it")
            self._file.attrs["schema_version"] = SCHEMA_VERSION
            if source_root is not None:  # `reradar cache --prune` drops files whose sequence folder is gone
                self._file.attrs[CACHE_SOURCE_ATTR] = str(Path(source_root).resolve())

    def get(self, name: str, source: Path | None) -> tuple[Prepared, float] | None:
        """Stored (record, compute_ms) for scan ``name``, or None if missing or its source file changed."""
        if self._file is None or name not in self._file:
            return None
        g = self._file[name]
        if "compute_ms" not in g.attrs:  # written last: a record interrupted mid-write is recomputed
            return None
        if source is not None and source.exists():
            size, mtime = _stamp(source)
            if int(g.attrs.get("size", -1)) != size or int(g.attrs.get("mtime_ns", -1)) != mtime:
                return None
        return {k: np.asarray(g[k][()]) for k in g.keys()}, float(g.attrs.get("compute_ms", float("nan")))

    def put(self, name: str, record: Prepared, compute_ms: float, source: Path | None) -> None:
        if self._file is None:
            return
        if name in self._file:
            del self._file[name]
        g = self._file.create_group(name)
        for k, v in record.items():
            g.create_dataset(k, data=np.asarray(v))
        g.attrs["compute_ms"] = float(compute_ms)
        if source is not None and source.exists():
            g.attrs["size"], g.attrs["mtime_ns"] = _stamp(source)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> FeatureCache:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
