"""Shared, memory-mapped map arrays: what a serving process needs of a map's keyframes, laid out once in one
flat file per map version, so that worker processes map the same page-cache pages instead of each holding a
private copy.

``reradar serve --workers N`` runs N processes; each used to read every keyframe from HDF5 into its own memory
(keypoints, local descriptors and the screen's bit-packed alignment masks: ~50 KB per keyframe with 512
landmarks). Here the first process to load a map writes those arrays, back to back, into
``<arrays_dir>/<map sha256>-<settings>.rrarr``; every process then ``mmap`` s the file read-only and its
keyframes are views into the mapping. The pages are the kernel's page cache, counted once however many
processes map them (measured in docs/BENCHMARKS.md, "Shared map arrays").

Safety:

- **keyed by content**: the file name carries the SHA-256 of the map file (read through the HDF5 library's own
  file descriptor, so it is the content of the file actually opened) and of the screen settings; a changed map
  (an update installed while serving) gets a new file, old processes keep their mapping of the old one;
- **written atomically**: temporary file + fsync + rename, under an exclusive ``flock`` so workers starting
  together build it once (the others wait, then map the result);
- **verified before use**: magic, format version, key, exact size and a BLAKE2b checksum of the payload are
  checked on every open (a read of the file, ~1 GB/s); a truncated or corrupt file is rebuilt, never served.
  The file is never modified in place, so a process that mapped it keeps valid data.

Layout (little-endian): 8-byte magic ``RRMAPARR``, uint32 format version, uint32 0, uint64 header length H,
H bytes of UTF-8 JSON (``key``, ``arrays``: name -> [dtype, shape, offset], ``payload_bytes``,
``payload_blake2b``), zero padding to ``_ALIGN``, then the payload (each array 64-byte aligned, offsets
relative to the payload's start).
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import mmap
import os
import struct
import threading
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from maps.store import KeyframeMap, _pid_alive, fsync_dir
from reradar_core.errors import MapFormatError
from reradar_core.features import ScanFeatures
from reradar_core.localization.screening import ScreenGrid, ScreenKeyframe, build_screen_grid
from reradar_core.matching import AlignmentConfig

__all__ = ["FORMAT_VERSION", "MapArrays", "arrays_file_name", "prune_arrays", "SUFFIX"]

logger = logging.getLogger(__name__)

#: Layout version; files of other versions are rebuilt.
FORMAT_VERSION = 1
SUFFIX = ".rrarr"
_MAGIC = b"RRMAPARR"
_PREFIX = struct.Struct("<8sIIQ")  # magic, version, reserved, header length
_ALIGN = 4096  # payload starts on a page
_ARRAY_ALIGN = 64
_CHUNK = 1 << 20


def _settings_tag(config: AlignmentConfig) -> str:
    """What the stored screen masks depend on (cell size, threshold), hashed into the file name."""
    text = json.dumps({"v": FORMAT_VERSION, "grid_cell_m": config.grid_cell_m,
                       "score_threshold_m": config.score_threshold_m}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def arrays_file_name(map_sha256: str, config: AlignmentConfig) -> str:
    """File name of the arrays of the map with content hash ``map_sha256`` under ``config``'s screen settings."""
    return f"{map_sha256[:40]}-{_settings_tag(config)}{SUFFIX}"


@contextmanager
def _exclusive(lock_path: Path) -> Iterator[None]:
    """An exclusive ``flock`` on ``lock_path`` (created if needed) for the block; released when it ends or the
    process dies."""
    fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


def _blake2b_fd(fd: int, start: int, length: int) -> str:
    h = hashlib.blake2b(digest_size=32)
    pos, end = start, start + length
    while pos < end:
        chunk = os.pread(fd, min(_CHUNK, end - pos), pos)
        if not chunk:
            break
        h.update(chunk)
        pos += len(chunk)
    return h.hexdigest()


class MapArrays:
    """A map's keyframe arrays, memory-mapped read-only from a verified arrays file; a ``KeyframeSource``
    (``reradar_core.localization.keyframes``) whose keyframes are views into the mapping, with their screen
    data (``read_screen``) precomputed.

    Open with ``MapArrays.open_or_build``. Attributes (all read-only arrays backed by the file):
        path: the arrays file; key: the key it was built for (map content hash + screen settings).
        timestamps_us: (N,) int64; poses: (N, 3) float64 ``T_map_keyframe`` (x m, y m, yaw rad);
        global_descriptors: (N, D) float32.
    """

    def __init__(self, path: Path, key: dict[str, object], arrays: dict[str, np.ndarray], mapping: mmap.mmap,
                 grid_cell_m: float, score_threshold_m: float) -> None:
        self.path = path
        self.key = key
        self._mmap = mapping
        self.timestamps_us = arrays["timestamps_us"]
        self.poses = arrays["poses"]
        self.global_descriptors = arrays["global_descriptors"]
        self._kp_offsets = arrays["keypoint_offsets"]
        self._keypoints = arrays["keypoints_xy_m"]
        self._local = arrays["local_descriptors"]
        self._grid_n = arrays["grid_n"]
        self._grid_origin = arrays["grid_origin_m"]
        self._mask_offsets = arrays["mask_offsets"]
        self._masks = arrays["masks"]
        self.grid_cell_m = grid_cell_m
        self.score_threshold_m = score_threshold_m

    def __len__(self) -> int:
        return int(self.poses.shape[0])

    @property
    def nbytes(self) -> int:
        """Size of the mapped file, bytes."""
        return len(self._mmap)

    def _check(self, index: int) -> None:
        if not 0 <= index < len(self):
            raise IndexError(f"keyframe {index} out of range [0, {len(self)})")

    def read_keyframe(self, index: int) -> ScanFeatures:
        """Keyframe ``index``'s features as views into the mapping (no copy)."""
        self._check(index)
        lo, hi = int(self._kp_offsets[index]), int(self._kp_offsets[index + 1])
        return ScanFeatures(self.global_descriptors[index], self._keypoints[lo:hi], self._local[lo:hi],
                            int(self.timestamps_us[index]))

    def read_screen(self, index: int, config: AlignmentConfig) -> ScreenKeyframe | None:
        """Keyframe ``index``'s ``ScreenKeyframe`` (views), or None when ``config``'s grid cell or score
        threshold differ from the stored masks' (the caller then builds its own)."""
        if config.grid_cell_m != self.grid_cell_m or config.score_threshold_m != self.score_threshold_m:
            return None
        self._check(index)
        lo, hi = int(self._kp_offsets[index]), int(self._kp_offsets[index + 1])
        mlo, mhi = int(self._mask_offsets[index]), int(self._mask_offsets[index + 1])
        grid = ScreenGrid(self._masks[mlo:mhi], int(self._grid_n[index]), float(self._grid_origin[index]),
                          self.grid_cell_m)
        return ScreenKeyframe(self._keypoints[lo:hi], self._local[lo:hi], grid)

    def close(self) -> None:
        """Drop this object's references to the mapping (the pages go when no array view is left)."""
        self.__dict__.pop("_mmap", None)

    # ---- opening -----------------------------------------------------------------------------------------
    @classmethod
    def open_or_build(cls, kf_map: KeyframeMap, arrays_dir: str | Path,
                      config: AlignmentConfig = AlignmentConfig()) -> MapArrays:
        """The verified arrays file of ``kf_map`` under ``arrays_dir``, built (once, atomically, under a file
        lock) when missing, stale or damaged.

        Raises:
            MapFormatError: the map's keyframes cannot be read, or the file written cannot be verified.
            OSError: ``arrays_dir`` cannot be created or written.
        """
        arrays_dir = Path(arrays_dir)
        arrays_dir.mkdir(parents=True, exist_ok=True)
        sha = kf_map.content_sha256()
        key = {"map_sha256": sha, "grid_cell_m": config.grid_cell_m, "score_threshold_m": config.score_threshold_m,
               "format": FORMAT_VERSION}
        path = arrays_dir / arrays_file_name(sha, config)
        opened, why = cls._try_open(path, key)
        if opened is not None:
            return opened
        with _exclusive(arrays_dir / f".{path.name}.lock"):
            opened, why = cls._try_open(path, key)  # another process may have built it while we waited
            if opened is not None:
                return opened
            if why != "missing":
                logger.warning("map arrays %s are unusable (%s); rebuilding them", path.name, why)
            t0 = time.perf_counter()
            _write(path, key, _collect(kf_map, config))
            logger.info("wrote map arrays %s for %s (%d keyframes, %.1f MB) in %.2f s", path.name,
                        kf_map.path.name, len(kf_map), path.stat().st_size / 1e6, time.perf_counter() - t0)
        opened, why = cls._try_open(path, key)
        if opened is None:
            raise MapFormatError(f"{kf_map.path.name}: the map arrays just written fail verification ({why})")
        return opened

    @classmethod
    def _try_open(cls, path: Path, key: dict[str, object]) -> tuple[MapArrays | None, str]:
        """(arrays, "") when ``path`` is a complete, verified arrays file for ``key``; else (None, why)."""
        try:
            fd = os.open(path, os.O_RDONLY)
        except FileNotFoundError:
            return None, "missing"
        try:
            size = os.fstat(fd).st_size
            prefix = os.pread(fd, _PREFIX.size, 0)
            if len(prefix) != _PREFIX.size:
                return None, "truncated header"
            magic, version, _, hlen = _PREFIX.unpack(prefix)
            if magic != _MAGIC or version != FORMAT_VERSION:
                return None, f"not a format-{FORMAT_VERSION} arrays file"
            if hlen > size or hlen > 1 << 24:
                return None, "truncated header"
            try:
                header = json.loads(os.pread(fd, hlen, _PREFIX.size).decode())
                start = _payload_start(hlen)
                payload = int(header["payload_bytes"])
                specs = header["arrays"]
            except (ValueError, KeyError, TypeError, UnicodeDecodeError):
                return None, "damaged header"
            if header.get("key") != key:
                return None, "built for another map version or settings"
            if size != start + payload:
                return None, f"size {size} B, expected {start + payload} B (truncated or extended)"
            if _blake2b_fd(fd, start, payload) != header.get("payload_blake2b"):
                return None, "checksum mismatch"
            mapping = mmap.mmap(fd, 0, access=mmap.ACCESS_READ)
        finally:
            os.close(fd)
        try:
            arrays = {name: np.frombuffer(mapping, np.dtype(dt), int(np.prod(shape, dtype=np.int64)),
                                          start + int(off)).reshape(shape)
                      for name, (dt, shape, off) in specs.items()}
            n = arrays["poses"].shape[0]
            if arrays["keypoint_offsets"].shape != (n + 1,) or arrays["mask_offsets"].shape != (n + 1,):
                return None, "inconsistent offsets"
        except (ValueError, KeyError, TypeError) as exc:
            return None, f"damaged array table ({exc})"
        return cls(path, key, arrays, mapping, float(key["grid_cell_m"]),  # type: ignore[arg-type]
                   float(key["score_threshold_m"])), ""  # type: ignore[arg-type]


def _payload_start(header_len: int) -> int:
    return -(-(_PREFIX.size + header_len) // _ALIGN) * _ALIGN


def _collect(kf_map: KeyframeMap, config: AlignmentConfig) -> dict[str, np.ndarray]:
    """Every array of the file, read from the HDF5 map (one pass over the keyframes)."""
    n = len(kf_map)
    kps, locs, masks, grid_n, grid_origin, globs = [], [], [], [], [], []
    for i in range(n):
        f = kf_map.read_keyframe(i)
        grid = build_screen_grid(f.keypoints_xy_m, config)
        kps.append(f.keypoints_xy_m)
        locs.append(f.local_descriptors)
        masks.append(grid.packed)
        grid_n.append(grid.n)
        grid_origin.append(grid.origin_m)
        globs.append(f.global_descriptor)
    c = kf_map.metadata.local_descriptor_dim
    return {
        "timestamps_us": np.asarray(kf_map.timestamps_us, np.int64),
        "poses": np.asarray(kf_map.poses, np.float64),
        "global_descriptors": np.asarray(np.stack(globs) if globs else
                                         np.zeros((0, kf_map.metadata.descriptor_dim)), np.float32),
        "keypoint_offsets": _offsets(len(k) for k in kps),
        "keypoints_xy_m": np.concatenate(kps).astype(np.float32) if kps else np.zeros((0, 2), np.float32),
        "local_descriptors": np.concatenate(locs).astype(np.float16) if locs else np.zeros((0, c), np.float16),
        "grid_n": np.asarray(grid_n, np.int64),
        "grid_origin_m": np.asarray(grid_origin, np.float64),
        "mask_offsets": _offsets(len(m) for m in masks),
        "masks": np.concatenate(masks).astype(np.uint8) if masks else np.zeros(0, np.uint8),
    }


def _offsets(lengths: Iterable[int]) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(list(lengths), dtype=np.int64)]).astype(np.int64)


def _write(path: Path, key: dict[str, object], arrays: dict[str, np.ndarray]) -> None:
    """Write the arrays file atomically: temporary file in the same folder, fsync, rename, fsync the folder."""
    specs: dict[str, list[object]] = {}
    off = 0
    for name, a in arrays.items():
        specs[name] = [a.dtype.str, list(a.shape), off]
        off += -(-a.nbytes // _ARRAY_ALIGN) * _ARRAY_ALIGN
    payload = off
    h = hashlib.blake2b(digest_size=32)
    for a in arrays.values():
        h.update(np.ascontiguousarray(a).tobytes())
        h.update(b"\0" * (-(-a.nbytes // _ARRAY_ALIGN) * _ARRAY_ALIGN - a.nbytes))
    header = json.dumps({"key": key, "arrays": specs, "payload_bytes": payload,
                         "payload_blake2b": h.hexdigest()}).encode()
    start = _payload_start(len(header))
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(_PREFIX.pack(_MAGIC, FORMAT_VERSION, 0, len(header)))
            fh.write(header)
            fh.write(b"\0" * (start - _PREFIX.size - len(header)))
            for a in arrays.values():
                fh.write(np.ascontiguousarray(a).tobytes())
                fh.write(b"\0" * (-(-a.nbytes // _ARRAY_ALIGN) * _ARRAY_ALIGN - a.nbytes))
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        fsync_dir(path.parent)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def prune_arrays(arrays_dir: str | Path, keep: Iterable[str], min_age_s: float = 600.0) -> list[Path]:
    """Delete arrays files (and their temporary and lock files) under ``arrays_dir`` not named in ``keep`` and
    not modified for ``min_age_s``. Safe while other processes map them: an unlinked file's pages stay valid for
    whoever has it mapped, and a process that opens it later rebuilds it. Returns the removed paths."""
    arrays_dir = Path(arrays_dir)
    keep = set(keep)
    removed: list[Path] = []
    if not arrays_dir.is_dir():
        return removed
    now = time.time()
    for p in arrays_dir.iterdir():
        if p.name in keep or not p.name.endswith((SUFFIX, ".tmp", ".lock")):
            continue
        if p.name.endswith(".lock") and p.name[1:-len(".lock")] in keep:  # the lock of a file in use
            continue
        if p.name.endswith(".tmp"):  # .<name>.<pid>.<thread>.tmp: never the file of a writer still running
            try:
                if _pid_alive(int(p.name.split(".")[-3])):
                    continue
            except (IndexError, ValueError):
                pass
        try:
            if now - p.stat().st_mtime < min_age_s:
                continue
            p.unlink()
            removed.append(p)
        except FileNotFoundError:
            continue
    if removed:
        logger.info("removed %d unused map arrays file(s) from %s", len(removed), arrays_dir)
    return removed
