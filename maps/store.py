"""HDF5 keyframe maps: the one module that touches h5py (schema in ``docs/MAP_FORMAT.md``).

A map holds, for N keyframes of one traversal:

- root attributes: ``schema_version``, ``model_id``, ``weights_sha256``, ``radar_preset``,
  ``cartesian_width_px``, ``cartesian_resolution_m``, ``descriptor_dim``, ``local_descriptor_dim``,
  ``num_keyframes``, ``created_utc`` (ISO 8601), ``source``, ``name``;
- ``/timestamps_us`` (N,) int64 and ``/poses`` (N, 3) float64 ``T_map_keyframe`` = (x m, y m, yaw rad);
- ``/global_descriptors`` (N, D) float32, L2-normalised rows;
- ``/keyframes/<i:06d>/keypoints_xy_m`` (K_i, 2) float32 (keyframe sensor frame, metres) and
  ``/keyframes/<i:06d>/local_descriptors`` (K_i, C) float16.

Writes go to a temporary file next to the target which is flushed, fsync'ed and renamed over the target
only when complete, so a crash mid-write never leaves a half map visible under the map's name.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import logging
import os
import threading
from dataclasses import asdict, dataclass
from pathlib import Path
from types import TracebackType

import h5py
import numpy as np

from reradar_core.bounds import MAX_ABS_COORDINATE_M
from reradar_core.errors import MapFormatError, ModelMismatchError
from reradar_core.features import ScanFeatures
from reradar_core.io.presets import PRESETS

__all__ = [
    "SCHEMA_VERSION",
    "POSE_TIME_MID_SWEEP",
    "POSE_TIME_FIRST_AZIMUTH",
    "MapMetadata",
    "KeyframeMap",
    "MapWriter",
    "open_map",
    "write_map",
    "install_file",
    "fsync_dir",
    "remove_stale_temp_files",
    "check_model",
    "read_metadata",
    "KEYPOINT_RANGE_MARGIN_M",
    "MAX_KEYPOINT_RANGE_M",
]

logger = logging.getLogger(__name__)

#: Version of the on-disk layout; readers refuse other versions.
SCHEMA_VERSION = 1
#: ``MapMetadata.pose_time`` values: keyframe poses at the scan's mid-sweep time (written now) or at its first
#: azimuth (maps from before 2026-11-30, which have no ``pose_time`` attribute).
POSE_TIME_MID_SWEEP = "mid_sweep"
POSE_TIME_FIRST_AZIMUTH = "first_azimuth"
#: Margin added to the longest radar range when validating keypoints, metres.
KEYPOINT_RANGE_MARGIN_M = 50.0
#: Largest accepted keypoint distance from its keyframe's sensor, metres: the longest maximum range of the radar
#: presets (``reradar_core.io.presets``; 199.9 m, Boreas) plus ``KEYPOINT_RANGE_MARGIN_M``. A landmark cannot lie
#: beyond the sensor's range, and a far keypoint would make the landmark grid built at load time grow with the
#: square of its distance (a keypoint at 2.5 km: ~1 GB).
MAX_KEYPOINT_RANGE_M = max(p.max_range_m for p in PRESETS.values()) + KEYPOINT_RANGE_MARGIN_M

_ATTR_FIELDS = (
    "schema_version",
    "model_id",
    "weights_sha256",
    "radar_preset",
    "cartesian_width_px",
    "cartesian_resolution_m",
    "descriptor_dim",
    "local_descriptor_dim",
    "num_keyframes",
    "created_utc",
    "source",
    "name",
)


@dataclass(frozen=True)
class MapMetadata:
    """Root attributes of a map file.

    Attributes:
        model_id: identifier of the descriptor model that produced the descriptors.
        weights_sha256: SHA-256 of the model weights; a running model with another hash cannot use the map.
        radar_preset: radar preset name of the scans (``boreas``, ``oxford``, ...).
        cartesian_width_px, cartesian_resolution_m: Cartesian image geometry the model used.
        descriptor_dim: D, global descriptor length.
        local_descriptor_dim: C, local descriptor length.
        num_keyframes: N.
        created_utc: ISO 8601 creation time (UTC).
        source: free text saying what the map was built from (a dataset path, an upload).
        name: human-readable map name.
        schema_version: layout version (``SCHEMA_VERSION`` when written by this code).
        pose_time: what time of each keyframe scan ``/poses`` refers to: ``mid_sweep`` (the mean azimuth time,
            docs/CONVENTIONS.md; written by this code) or ``first_azimuth`` (maps written before the attribute
            existed: their poses sit half a sweep back along the track, ~1 m at 8 m/s; opening one logs a
            warning - rebuild it).
    """

    model_id: str
    weights_sha256: str
    radar_preset: str
    cartesian_width_px: int
    cartesian_resolution_m: float
    descriptor_dim: int
    local_descriptor_dim: int
    num_keyframes: int = 0
    created_utc: str = ""
    source: str = ""
    name: str = ""
    schema_version: int = SCHEMA_VERSION
    pose_time: str = POSE_TIME_MID_SWEEP

    def to_dict(self) -> dict[str, object]:
        return asdict(self)


def check_model(metadata: MapMetadata, model_id: str, weights_sha256: str, path: str | Path = "map") -> None:
    """Refuse a map built by another model (its descriptors are not comparable with ours).

    Raises:
        ModelMismatchError: the map's weights hash differs from ``weights_sha256``.
    """
    if metadata.weights_sha256 != weights_sha256:
        raise ModelMismatchError(
            f"{path}: map was built with model {metadata.model_id!r} (weights sha256 "
            f"{metadata.weights_sha256[:12]}...) but the running model is {model_id!r} "
            f"({weights_sha256[:12]}...); its descriptors are incomparable - rebuild the map with "
            f"`reradar build-map` using the current model"
        )


def _dataset(group: h5py.Group, name: str, path: Path) -> h5py.Dataset:
    """``group[name]`` if it is a plain dataset stored in this file.

    Uploaded maps are untrusted: soft/external links, external raw storage and virtual datasets could make
    the server read other files, so they are refused.
    """
    link = group.get(name, getlink=True)
    if link is None:
        raise MapFormatError(f"{path}: map has no '{group.name.rstrip('/')}/{name}'")
    if not isinstance(link, h5py.HardLink):
        raise MapFormatError(f"{path}: '{group.name.rstrip('/')}/{name}' is a link; maps must be self-contained")
    ds = group[name]
    if not isinstance(ds, h5py.Dataset):
        raise MapFormatError(f"{path}: '{ds.name}' is not a dataset")
    if ds.external or ds.is_virtual:
        raise MapFormatError(f"{path}: '{ds.name}' uses external or virtual storage; maps must be self-contained")
    return ds


def _check_links(f: h5py.File, path: Path) -> None:
    """Refuse a file holding any soft, external or user-defined link, anywhere (links are listed, never
    followed): uploaded maps are untrusted and must be self-contained (~3 us per link)."""
    found: list[str] = []

    def visit(name: bytes, info: h5py.h5l.LinkInfo) -> int | None:
        if info.type != h5py.h5l.TYPE_HARD:
            kind = {h5py.h5l.TYPE_SOFT: "a soft link", h5py.h5l.TYPE_EXTERNAL: "an external link"}.get(
                info.type, "a link")
            found.append(f"'/{name.decode(errors='replace')}' is {kind}")
            return 1  # stop at the first one
        return None

    f.id.links.visit(visit, info=True)
    if found:
        raise MapFormatError(f"{path}: {found[0]}; maps must be self-contained (no soft or external links)")


def _check_keyframe(kps: np.ndarray, desc: np.ndarray, path: Path, index: int) -> None:
    """Refuse keypoints that are not finite or lie beyond ``MAX_KEYPOINT_RANGE_M`` of the sensor, and local
    descriptors that are not finite. ``kps`` (K, 2) float32 metres, ``desc`` (K, C) float16."""
    if kps.ndim != 2 or kps.shape[-1] != 2:
        raise MapFormatError(f"{path}: keyframe {index}: keypoints_xy_m has shape {kps.shape}, expected (K, 2)")
    if not np.all(np.isfinite(kps)):
        raise MapFormatError(f"{path}: keyframe {index}: keypoints_xy_m contain NaN/inf; keypoints must be finite")
    if kps.size:
        far = float(np.max(np.hypot(kps[:, 0].astype(np.float64), kps[:, 1].astype(np.float64))))
        if far > MAX_KEYPOINT_RANGE_M:
            raise MapFormatError(
                f"{path}: keyframe {index}: a keypoint lies {far:.4g} m from the sensor; keypoints must be within "
                f"the radar's range ({MAX_KEYPOINT_RANGE_M:.0f} m)")
    if not np.all(np.isfinite(desc)):
        raise MapFormatError(f"{path}: keyframe {index}: local_descriptors contain NaN/inf")


def _read_metadata(f: h5py.File, path: Path) -> MapMetadata:
    attrs = f.attrs
    if "schema_version" not in attrs:
        raise MapFormatError(f"{path}: not a ReRadar map (no schema_version attribute)")
    version = int(attrs["schema_version"])
    if version != SCHEMA_VERSION:
        raise MapFormatError(
            f"{path}: map schema_version {version} is not supported (this build reads {SCHEMA_VERSION}); "
            f"rebuild the map with `reradar build-map`"
        )
    missing = [k for k in _ATTR_FIELDS if k not in attrs]
    if missing:
        raise MapFormatError(f"{path}: map is missing root attributes {missing}")

    def s(key: str) -> str:
        v = attrs[key]
        return v.decode() if isinstance(v, bytes) else str(v)

    return MapMetadata(
        model_id=s("model_id"),
        weights_sha256=s("weights_sha256"),
        radar_preset=s("radar_preset"),
        cartesian_width_px=int(attrs["cartesian_width_px"]),
        cartesian_resolution_m=float(attrs["cartesian_resolution_m"]),
        descriptor_dim=int(attrs["descriptor_dim"]),
        local_descriptor_dim=int(attrs["local_descriptor_dim"]),
        num_keyframes=int(attrs["num_keyframes"]),
        created_utc=s("created_utc"),
        source=s("source"),
        name=s("name"),
        schema_version=version,
        pose_time=_pose_time(attrs, path),
    )


def _pose_time(attrs: h5py.AttributeManager, path: Path) -> str:
    """The map's ``pose_time`` attribute; ``first_azimuth`` (with a warning) for maps written without it."""
    if "pose_time" not in attrs:
        logger.warning("%s: map has no pose_time attribute - its keyframe poses are first-azimuth poses, half a "
                       "sweep behind the mid-sweep poses answers refer to (docs/CONVENTIONS.md); rebuild it",
                       path.name)
        return POSE_TIME_FIRST_AZIMUTH
    v = attrs["pose_time"]
    value = v.decode() if isinstance(v, bytes) else str(v)
    if value not in (POSE_TIME_MID_SWEEP, POSE_TIME_FIRST_AZIMUTH):
        raise MapFormatError(f"{path}: unknown pose_time {value!r} (expected {POSE_TIME_MID_SWEEP!r})")
    return value


def _open_h5(path: Path) -> h5py.File:
    if not path.is_file():
        raise MapFormatError(f"{path}: no such map file")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise MapFormatError(f"{path}: not a readable HDF5 map ({exc})") from exc


def read_metadata(path: str | Path) -> MapMetadata:
    """Read only the root attributes of the map at ``path`` (cheap; validates the schema version)."""
    path = Path(path)
    with _open_h5(path) as f:
        return _read_metadata(f, path)


class KeyframeMap:
    """A map opened for reading.

    Poses, timestamps and global descriptors are loaded into memory at open (they feed the FAISS index);
    keypoints and local descriptors stay on disk and are read per keyframe by ``read_keyframe`` (only the
    candidates of a query). Thread-safe: reads are serialised by a lock (h5py is not re-entrant).

    Attributes:
        path: the map file.
        metadata: root attributes.
        timestamps_us: (N,) int64.
        poses: (N, 3) float64 ``T_map_keyframe`` (x m, y m, yaw rad).
        global_descriptors: (N, D) float32.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self._sha256: str | None = None
        self._file: h5py.File | None = _open_h5(self.path)
        self.global_descriptors: np.ndarray | None
        try:
            _check_links(self._file, self.path)
            self.metadata = _read_metadata(self._file, self.path)
            self.timestamps_us, self.poses, self.global_descriptors = self._read_arrays(self._file)
        except MapFormatError:
            self.close()
            raise
        except (KeyError, OSError, ValueError, TypeError) as exc:
            self.close()
            raise MapFormatError(f"{self.path}: corrupt map ({exc})") from exc

    def _read_arrays(self, f: h5py.File) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = self.metadata.num_keyframes
        d = self.metadata.descriptor_dim
        if not isinstance(f.get("keyframes", getlink=True), h5py.HardLink) or not isinstance(f["keyframes"], h5py.Group):
            raise MapFormatError(f"{self.path}: map has no '/keyframes' group")
        ts = np.asarray(_dataset(f, "timestamps_us", self.path)[()], dtype=np.int64)
        poses_ds = _dataset(f, "poses", self.path)
        if poses_ds.dtype != np.float64:
            raise MapFormatError(f"{self.path}: /poses must be float64, found {poses_ds.dtype}")
        poses = np.asarray(poses_ds[()], dtype=np.float64)
        g = np.asarray(_dataset(f, "global_descriptors", self.path)[()], dtype=np.float32)
        if ts.shape != (n,) or poses.shape != (n, 3) or g.shape != (n, d):
            raise MapFormatError(
                f"{self.path}: inconsistent shapes: timestamps {ts.shape}, poses {poses.shape}, "
                f"global descriptors {g.shape} for num_keyframes={n}, descriptor_dim={d}"
            )
        if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(g))):
            raise MapFormatError(f"{self.path}: poses or descriptors contain NaN/inf")
        if np.any(np.abs(poses[:, :2]) > MAX_ABS_COORDINATE_M):
            raise MapFormatError(f"{self.path}: keyframe poses must lie within +-{MAX_ABS_COORDINATE_M:.0e} m of "
                                 f"the map origin")
        if len(f["keyframes"]) != n:
            raise MapFormatError(f"{self.path}: {len(f['keyframes'])} keyframe groups for {n} keyframes")
        return ts, poses, np.ascontiguousarray(g)

    def __len__(self) -> int:
        return self.metadata.num_keyframes

    def read_keyframe(self, index: int) -> ScanFeatures:
        """Features of keyframe ``index`` (keypoints in its sensor frame, metres; float16 descriptors).

        Raises:
            IndexError: ``index`` out of range.
            MapFormatError: the keyframe group is damaged or the map was closed.
        """
        if not 0 <= index < len(self):
            raise IndexError(f"keyframe {index} out of range [0, {len(self)})")
        with self._lock:
            if self._file is None:
                raise MapFormatError(f"{self.path}: map is closed")
            try:
                kgroup = self._file["keyframes"]
                name = f"{index:06d}"
                if not isinstance(kgroup.get(name, getlink=True), h5py.HardLink):
                    raise MapFormatError(f"{self.path}: keyframe {index} is missing or a link")
                grp = kgroup[name]
                kps = np.asarray(_dataset(grp, "keypoints_xy_m", self.path)[()], dtype=np.float32)
                desc = np.asarray(_dataset(grp, "local_descriptors", self.path)[()], dtype=np.float16)
                if self.global_descriptors is not None:
                    g = self.global_descriptors[index]
                else:  # released after indexing: read the one row from disk
                    g = np.asarray(_dataset(self._file, "global_descriptors", self.path)[index], dtype=np.float32)
            except MapFormatError:
                raise
            except (KeyError, OSError, ValueError) as exc:
                raise MapFormatError(f"{self.path}: keyframe {index} is damaged ({exc})") from exc
        _check_keyframe(kps, desc, self.path, index)
        try:
            return ScanFeatures(g, kps, desc, int(self.timestamps_us[index]))
        except ValueError as exc:
            raise MapFormatError(f"{self.path}: keyframe {index}: {exc}") from exc

    def content_sha256(self) -> str:
        """SHA-256 of the map file's bytes, read through the HDF5 library's own file descriptor (so it is the
        content of the file this object opened, even if another file was renamed over ``path`` since);
        computed once (~1 s per GB)."""
        with self._lock:
            if self._sha256 is None:
                if self._file is None:
                    raise MapFormatError(f"{self.path}: map is closed")
                fd = int(self._file.id.get_vfd_handle())
                h = hashlib.sha256()
                pos = 0
                while chunk := os.pread(fd, 1 << 20, pos):
                    h.update(chunk)
                    pos += len(chunk)
                self._sha256 = h.hexdigest()
            return self._sha256

    def release_global_descriptors(self) -> None:
        """Drop the in-memory (N, D) global descriptors once an index holds them (halves resident memory);
        ``read_keyframe`` then reads a keyframe's row from disk."""
        self.global_descriptors = None

    def close(self) -> None:
        with self._lock:
            if self._file is not None:
                self._file.close()
                self._file = None

    def __enter__(self) -> KeyframeMap:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_map(path: str | Path, model_id: str | None = None, weights_sha256: str | None = None) -> KeyframeMap:
    """Open the map at ``path``; if ``weights_sha256`` is given, refuse a map built by another model.

    Raises:
        MapFormatError: unreadable / wrong schema / inconsistent file.
        ModelMismatchError: built with other weights.
    """
    kf_map = KeyframeMap(path)
    if weights_sha256 is not None:
        try:
            check_model(kf_map.metadata, model_id or "?", weights_sha256, kf_map.path)
        except ModelMismatchError:
            kf_map.close()
            raise
    return kf_map


def fsync_dir(directory: str | Path) -> None:
    """Make a rename / creation / deletion in ``directory`` durable (no-op where the filesystem refuses)."""
    try:
        dir_fd = os.open(directory, os.O_RDONLY)
    except OSError:  # pragma: no cover
        return
    try:
        os.fsync(dir_fd)
    except OSError:  # pragma: no cover - some filesystems refuse directory fsync
        pass
    finally:
        os.close(dir_fd)


def install_file(src: str | Path, dst: str | Path) -> Path:
    """Durably move a complete file into place: fsync ``src``, rename it over ``dst`` (atomic within one
    filesystem), fsync both folders. After a crash ``dst`` is either the old file or the whole new one."""
    src, dst = Path(src), Path(dst)
    with open(src, "rb+") as fh:
        os.fsync(fh.fileno())
    os.replace(src, dst)
    fsync_dir(dst.parent)
    if src.parent != dst.parent:
        fsync_dir(src.parent)
    return dst


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def remove_stale_temp_files(directory: str | Path) -> list[Path]:
    """Delete ``.<name>.<pid>.<thread>.tmp`` files in ``directory`` left by map writers whose process is gone
    (killed mid-write); files of live processes are kept. Returns the removed paths."""
    removed = []
    for tmp in Path(directory).glob(".*.tmp"):
        parts = tmp.name.split(".")
        try:
            pid = int(parts[-3])
        except (IndexError, ValueError):
            continue
        if pid != os.getpid() and not _pid_alive(pid):
            tmp.unlink(missing_ok=True)
            removed.append(tmp)
    if removed:
        logger.info("removed %d temporary map file(s) left by killed writers in %s", len(removed), directory)
    return removed


class MapWriter:
    """Streaming, atomic map writer.

    Use as a context manager: ``add`` keyframes in batches, the file appears under ``path`` only when the
    ``with`` block exits without an exception (temporary file + flush + fsync + rename); on error the
    temporary file is deleted and any existing map at ``path`` is left untouched.
    """

    def __init__(self, path: str | Path, metadata: MapMetadata, overwrite: bool = False) -> None:
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise FileExistsError(f"{self.path}: map already exists (pass overwrite=True to replace it)")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.metadata = metadata
        remove_stale_temp_files(self.path.parent)  # left by a writer killed earlier (kill -9, power loss)
        self._tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        self._file: h5py.File | None = None
        self._ts: list[int] = []
        self._poses: list[np.ndarray] = []
        self._glob: list[np.ndarray] = []
        self._n = 0

    def __enter__(self) -> MapWriter:
        self._file = h5py.File(self._tmp, "w")
        self._file.create_group("keyframes")
        return self

    def add(self, features: ScanFeatures, pose: np.ndarray, timestamp_us: int | None = None) -> int:
        """Append one keyframe with its map pose ``T_map_keyframe`` (3,) (x m, y m, yaw rad); returns its id."""
        if self._file is None:
            raise RuntimeError("MapWriter.add outside its with-block")
        pose = np.asarray(pose, dtype=np.float64).reshape(-1)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise ValueError(f"keyframe pose must be 3 finite values (x, y, yaw), got {pose}")
        g = np.asarray(features.global_descriptor, dtype=np.float32)
        if g.shape != (self.metadata.descriptor_dim,):
            raise ValueError(f"global descriptor has shape {g.shape}, map expects ({self.metadata.descriptor_dim},)")
        c = features.local_descriptors.shape[1]
        if features.keypoints_xy_m.shape[0] and c != self.metadata.local_descriptor_dim:
            raise ValueError(f"local descriptors have {c} channels, map expects {self.metadata.local_descriptor_dim}")
        grp = self._file["keyframes"].create_group(f"{self._n:06d}")
        grp.create_dataset("keypoints_xy_m", data=features.keypoints_xy_m.astype(np.float32))
        local = features.local_descriptors.astype(np.float16)
        if local.shape[0] == 0:
            local = np.zeros((0, self.metadata.local_descriptor_dim), np.float16)
        grp.create_dataset("local_descriptors", data=local)
        self._ts.append(int(features.timestamp_us if timestamp_us is None else timestamp_us))
        self._poses.append(pose)
        self._glob.append(g)
        self._n += 1
        return self._n - 1

    def __len__(self) -> int:
        return self._n

    def _finalize(self) -> None:
        assert self._file is not None
        f = self._file
        d = self.metadata.descriptor_dim
        f.create_dataset("timestamps_us", data=np.asarray(self._ts, dtype=np.int64).reshape(self._n))
        f.create_dataset("poses", data=np.asarray(self._poses, dtype=np.float64).reshape(self._n, 3))
        f.create_dataset("global_descriptors", data=np.asarray(self._glob, dtype=np.float32).reshape(self._n, d))
        meta = self.metadata.to_dict()
        meta["num_keyframes"] = self._n
        meta["schema_version"] = SCHEMA_VERSION
        if not meta["created_utc"]:
            meta["created_utc"] = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
        for key in (*_ATTR_FIELDS, "pose_time"):
            f.attrs[key] = meta[key]
        f.flush()
        f.close()
        self._file = None
        install_file(self._tmp, self.path)

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is None:
            try:
                self._finalize()
                return
            except BaseException:
                self._abort()
                raise
        self._abort()

    def _abort(self) -> None:
        if self._file is not None:
            try:
                self._file.close()
            except Exception:  # noqa: BLE001 - best effort while already failing
                logger.debug("closing temporary map %s failed", self._tmp)
            self._file = None
        self._tmp.unlink(missing_ok=True)


def write_map(path: str | Path, metadata: MapMetadata, features: list[ScanFeatures], poses: np.ndarray,
              overwrite: bool = False) -> Path:
    """Write a whole map at once (atomic). ``poses`` (N, 3) float64 ``T_map_keyframe``. Returns ``path``."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if len(features) != poses.shape[0]:
        raise ValueError(f"{len(features)} keyframes but {poses.shape[0]} poses")
    with MapWriter(path, metadata, overwrite=overwrite) as w:
        for feat, pose in zip(features, poses, strict=True):
            w.add(feat, pose)
    return Path(path)
