"""HDF5 keyframe maps: the one module that touches h5py (schema in ``docs/MAP_FORMAT.md``).

A map holds, for N keyframes of one traversal:

- root attributes: ``schema_version``, ``model_id``, ``weights_sha256``, ``radar_preset``,
  ``cartesian_width_px``, ``cartesian_resolution_m``, ``descriptor_dim``, ``local_descriptor_dim``,
  ``num_keyframes``, ``created_utc`` (ISO 8601), ``source``, ``name``;
- ``/timestamps_us`` (N,) int64 and ``/poses`` (N, 3) float64 ``T_map_keyframe`` = (x m, y m, yaw rad);
- ``/global_descriptors`` (N, D) float32, L2-normalised rows;
- ``/keyframes/<i:06d>/keypoints_xy_m`` (K_i, 2) float32 (keyframe sensor frame, metres) and
  ``/keyframes/<i:06d>/local_descriptors`` (K_i, C) float16;
- optionally ``/place_repetition``: every keyframe's measured place repetition (``RepetitionTable``: datasets
  ``neighbour_score``, ``rival_score`` (N,) float64, ``rival_keyframe_id`` (N,) int64, attribute ``settings``), which
  ``reradar build-map`` writes so that no query pays for measuring it.

Writes go to a temporary file next to the target which is flushed, fsync'ed and renamed over the target
only when complete, so a crash mid-write never leaves a half map visible under the map's name.
"""

from __future__ import annotations

import datetime as _dt
import errno
import hashlib
import logging
import mmap
import os
import re
import struct
import subprocess
import sys
import threading
from dataclasses import asdict, dataclass
from pathlib import Path
from types import TracebackType

import h5py
import numpy as np

from reradar_core.bounds import MAX_ABS_COORDINATE_M
from reradar_core.errors import ConfigError, MapFormatError, ModelMismatchError
from reradar_core.features import ScanFeatures
from reradar_core.io.presets import PRESETS
from reradar_core.localization.repetition import RepetitionTable

__all__ = [
    "SCHEMA_VERSION",
    "POSE_TIME_MID_SWEEP",
    "POSE_TIME_FIRST_AZIMUTH",
    "MapMetadata",
    "KeyframeMap",
    "MapWriter",
    "open_map",
    "write_map",
    "store_place_repetition",
    "install_file",
    "fsync_dir",
    "remove_stale_temp_files",
    "check_model",
    "read_metadata",
    "KEYPOINT_RANGE_MARGIN_M",
    "MAX_KEYPOINT_RANGE_M",
    "UNKNOWN_RADAR_PRESET",
    "MAX_DESCRIPTOR_DIM",
    "MAX_LOCAL_DESCRIPTOR_DIM",
    "MAX_KEYPOINTS_PER_KEYFRAME",
    "MAX_STORAGE_EXPANSION",
    "DESCRIPTOR_NORM_TOLERANCE",
    "MAX_REPETITION_SETTINGS_CHARS",
    "PROBE_TIMEOUT_S",
    "probe_map",
    "DENSE_IMAGES_ATTR",
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
#: ``radar_preset`` of a map built from scans whose preset was not known (``MapRegistry.start_build``,
#: ``BuildQueue``); the only accepted value that is not a name of ``reradar_core.io.presets.PRESETS``.
UNKNOWN_RADAR_PRESET = "unknown"
#: Largest accepted ``descriptor_dim`` and ``local_descriptor_dim`` (the shipped model: 256 and 32); they size
#: arrays read at open, so an absurd value is refused before anything is read.
MAX_DESCRIPTOR_DIM = 4096
MAX_LOCAL_DESCRIPTOR_DIM = 1024
#: Largest accepted keypoint count of one keyframe: more than one per pixel of any Cartesian image a model
#: describes (the shipped model keeps 512 of a 201 x 201 image).
MAX_KEYPOINTS_PER_KEYFRAME = 65_536
#: A dataset may declare at most this many times the bytes the file stores for it (plus
#: ``_STORAGE_SLACK_BYTES``): an HDF5 dataset whose chunks were never written, or that compresses 1000:1, reads
#: as gigabytes of fill value from a small upload. Map data (floats) compresses less than 4:1.
MAX_STORAGE_EXPANSION = 32
_STORAGE_SLACK_BYTES = 4096
#: Accepted deviation of a global descriptor's L2 norm from 1 (float32 rounding is ~1e-7); unit rows keep the
#: descriptor distance ``sqrt(2 - 2 <a, b>)`` within [0, 2].
DESCRIPTOR_NORM_TOLERANCE = 1e-3
#: Longest accepted ``/place_repetition`` ``settings`` attribute, characters (the shipped settings: ~700).
MAX_REPETITION_SETTINGS_CHARS = 16_384
_INT64_MAX = int(np.iinfo(np.int64).max)
#: Root attribute of a map whose every keyframe stores ``/keyframes/<i>/dense_image`` (a far-view companion built
#: since 2026-12-04): the settings the images were made with (``matching.dense.dense_image_settings``).
DENSE_IMAGES_ATTR = "dense_images"

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


#: the image-size part of a model id (``-in201``, ``-in257``): compared through the map's image attributes instead
_IMAGE_SIZE_ID = re.compile(r"-in\d+(?=-|$)")


def check_model(metadata: MapMetadata, model_id: str, weights_sha256: str, path: str | Path = "map") -> None:
    """Refuse a map built by another model (its descriptors are not comparable with ours).

    ``model_id`` ("?" or empty: not checked) must equal the map's up to its image size (``-in<px>``, which the
    service compares with the map's image attributes, ``MapRegistry.check_compatible``, saying which images differ):
    the same weights describe a scan differently under another option (``ModelConfig.model_id``: the canonical
    heading's ``-ch``), so a map described without the canonical heading is refused by a model that uses it, and the
    other way round.

    Raises:
        ModelMismatchError: the map's weights hash differs from ``weights_sha256``, or its model id from
            ``model_id``.
    """
    if (metadata.weights_sha256 == weights_sha256 and model_id not in ("", "?")
            and _IMAGE_SIZE_ID.sub("", metadata.model_id) != _IMAGE_SIZE_ID.sub("", model_id)):
        raise ModelMismatchError(
            f"{path}: map was described as {metadata.model_id!r} but the running model describes scans as "
            f"{model_id!r} (the same weights with another option, e.g. the canonical heading of model ids ending "
            f"in '-ch'); its descriptors are incomparable - rebuild the map with `reradar build-map` using "
            f"the current model"
        )
    if metadata.weights_sha256 != weights_sha256:
        raise ModelMismatchError(
            f"{path}: map was built with model {metadata.model_id!r} (weights sha256 "
            f"{metadata.weights_sha256[:12]}...) but the running model is {model_id!r} "
            f"({weights_sha256[:12]}...); its descriptors are incomparable - rebuild the map with "
            f"`reradar build-map` using the current model"
        )


#: What h5py raises on a damaged file or object (a corrupt header, a truncated file, a member of the wrong kind);
#: every read path turns them into ``MapFormatError``, so a bad upload is refused (422), never a server error.
_H5_ERRORS = (KeyError, OSError, RuntimeError, TypeError, ValueError)


def _h5_reason(exc: BaseException, path: Path) -> str:
    """The HDF5 library's reason for ``exc``, without the server folder of ``path`` (open errors may name it)."""
    text = str(exc) or type(exc).__name__
    for full in {str(path.resolve()), str(path)}:
        text = text.replace(full, path.name)
    return text


def _dataset(group: h5py.Group, name: str, path: Path) -> h5py.Dataset:
    """``group[name]`` if it is a plain dataset stored in this file (its data is not read).

    Uploaded maps are untrusted: soft/external links, external raw storage and virtual datasets could make
    the server read other files, so they are refused.
    """
    if not isinstance(group, h5py.Group):
        raise MapFormatError(f"{path}: '{group.name}' is not a group")
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


def _check_layout(ds: h5py.Dataset, shape: tuple[int, ...], kinds: str, dtype_name: str, path: Path,
                  meaning: str) -> None:
    """Refuse ``ds`` unless it has ``shape`` and a dtype of a numpy kind in ``kinds`` (``i``/``u`` integers, ``f``
    floats). Only the dataset's header is consulted: a declared-huge dataset is refused before it is read.
    ``meaning`` says where ``shape`` comes from, for the message."""
    if ds.shape != shape:
        raise MapFormatError(f"{path}: '{ds.name}' has shape {ds.shape}, expected {shape} ({meaning})")
    if ds.dtype.kind not in kinds:
        raise MapFormatError(f"{path}: '{ds.name}' has dtype {ds.dtype}, expected {dtype_name}")


def _check_stored(ds: h5py.Dataset, path: Path) -> None:
    """Refuse a dataset that declares more than ``MAX_STORAGE_EXPANSION`` times the bytes the file stores for it
    (header only): chunks never written read as fill value, so a small file could fill the server's memory."""
    declared = int(ds.size) * ds.dtype.itemsize
    if declared <= _STORAGE_SLACK_BYTES:
        return
    stored = int(ds.id.get_storage_size())
    if declared > MAX_STORAGE_EXPANSION * stored + _STORAGE_SLACK_BYTES:
        raise MapFormatError(
            f"{path}: '{ds.name}' declares {declared} bytes of data but the file stores {stored} bytes for it; "
            f"datasets must be written in full (compressed at most {MAX_STORAGE_EXPANSION}:1)")


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


def _check_keyframe_datasets(kps: h5py.Dataset, desc: h5py.Dataset, local_dim: int, path: Path,
                             index: int) -> None:
    """Header checks of keyframe ``index``'s datasets, before they are read: ``keypoints_xy_m`` (K, 2) float with
    K <= ``MAX_KEYPOINTS_PER_KEYFRAME``, ``local_descriptors`` (K, ``local_dim``) float, both stored in full."""
    if kps.shape is None or len(kps.shape) != 2 or kps.shape[1] != 2:
        raise MapFormatError(f"{path}: keyframe {index}: keypoints_xy_m has shape {kps.shape}, expected (K, 2)")
    k = int(kps.shape[0])
    if k > MAX_KEYPOINTS_PER_KEYFRAME:
        raise MapFormatError(f"{path}: keyframe {index} has {k} keypoints; at most {MAX_KEYPOINTS_PER_KEYFRAME} "
                             f"per keyframe are accepted")
    if kps.dtype.kind != "f":
        raise MapFormatError(f"{path}: '{kps.name}' has dtype {kps.dtype}, expected float32")
    _check_layout(desc, (k, local_dim), "f", "float16", path,
                  f"one row of local_descriptor_dim = {local_dim} values per keypoint")
    _check_stored(kps, path)
    _check_stored(desc, path)


def _check_keyframe(kps: np.ndarray, desc: np.ndarray, path: Path, index: int) -> None:
    """Refuse keypoints that are not finite or lie beyond ``MAX_KEYPOINT_RANGE_M`` of the sensor, and local
    descriptors that are not finite. ``kps`` (K, 2) float32 metres, ``desc`` (K, C) float16; their shapes were
    checked on the datasets' headers before they were read (``_check_keyframe_datasets``)."""
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


def _check_timestamps(ts: np.ndarray, path: Path) -> np.ndarray:
    """``/timestamps_us`` (N,) of an integer dtype as int64, refused unless non-negative, within int64 and unique
    (each keyframe is a scan of its own time; the builder writes them in drive order, increasing, but a map may
    hold its keyframes in another order)."""
    if ts.size and (int(ts.min()) < 0 or int(ts.max()) > _INT64_MAX):
        raise MapFormatError(f"{path}: /timestamps_us must be non-negative microseconds within int64, found "
                             f"{int(ts.min())} .. {int(ts.max())}")
    ts = ts.astype(np.int64)
    ordered = np.sort(ts)
    repeated = ordered[1:][ordered[1:] == ordered[:-1]]
    if repeated.size:
        raise MapFormatError(f"{path}: keyframe timestamp {int(repeated[0])} us appears more than once in "
                             f"/timestamps_us; each keyframe needs its own scan time")
    return ts


def _check_global_descriptors(g: np.ndarray, path: Path) -> None:
    """Refuse global descriptors (N, D) float32 that are not finite or not L2-normalised
    (``DESCRIPTOR_NORM_TOLERANCE``): the index compares them by inner product."""
    if not np.all(np.isfinite(g)):
        raise MapFormatError(f"{path}: /global_descriptors contain NaN/inf (or values beyond float32)")
    norms = np.sqrt(np.einsum("ij,ij->i", g, g, dtype=np.float64))
    bad = np.flatnonzero(np.abs(norms - 1.0) > DESCRIPTOR_NORM_TOLERANCE)
    if bad.size:
        i = int(bad[0])
        raise MapFormatError(
            f"{path}: the global descriptor of keyframe {i} has L2 norm {norms[i]:.6g}; global descriptors must be "
            f"L2-normalised (norm 1 +- {DESCRIPTOR_NORM_TOLERANCE:g})")


def _show(value: object) -> str:
    if isinstance(value, np.generic):  # np.float64(0.0) -> 0.0
        value = value.item()
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _attr_value(attrs: h5py.AttributeManager, key: str, path: Path, owner: str = "root") -> object:
    """Attribute ``key`` (of the root, or of the group named by ``owner``) as one value; its shape is checked before
    it is read (an attribute may hold an array of any size)."""
    shape = attrs.get_id(key).shape
    if shape not in ((), (1,)):
        raise MapFormatError(f"{path}: {owner} attribute {key!r} must be a single value, found shape {shape}")
    value = attrs[key]
    return value.reshape(-1)[0] if isinstance(value, np.ndarray) else value


def _text_attr(attrs: h5py.AttributeManager, key: str, path: Path, owner: str = "root") -> str:
    """Attribute ``key`` (of the root, or of the group ``owner``) as text of at most ``MAX_REPETITION_SETTINGS_CHARS``
    characters (a settings record: ``/place_repetition``'s, ``dense_images``); anything else is a MapFormatError."""
    value = _attr_value(attrs, key, path, owner)
    if not isinstance(value, (str, bytes)):
        raise MapFormatError(f"{path}: {owner} attribute {key!r} must be text, found {type(value).__name__}")
    text = value.decode(errors="replace") if isinstance(value, bytes) else value
    if len(text) > MAX_REPETITION_SETTINGS_CHARS:
        raise MapFormatError(f"{path}: {owner} attribute {key!r} holds {len(text)} characters; at most "
                             f"{MAX_REPETITION_SETTINGS_CHARS} are accepted")
    return text


def _str_attr(attrs: h5py.AttributeManager, key: str, path: Path) -> str:
    value = _attr_value(attrs, key, path)
    return value.decode(errors="replace") if isinstance(value, bytes) else str(value)


def _int_attr(attrs: h5py.AttributeManager, key: str, path: Path, low: int, high: int | None = None) -> int:
    """Root attribute ``key`` as an int in [``low``, ``high``] (an integral float is accepted)."""
    value = _attr_value(attrs, key, path)
    integral = isinstance(value, int | np.integer) or (
        isinstance(value, float | np.floating) and np.isfinite(value) and float(value).is_integer())
    if isinstance(value, bool | np.bool_) or not integral:
        raise MapFormatError(f"{path}: root attribute {key!r} must be an integer, found {_show(value)}")
    number = int(value)  # type: ignore[call-overload]
    if number < low or (high is not None and number > high):
        bound = f"between {low} and {high}" if high is not None else f">= {low}"
        raise MapFormatError(f"{path}: root attribute {key} = {number} must be {bound}")
    return number


def _positive_float_attr(attrs: h5py.AttributeManager, key: str, path: Path) -> float:
    value = _attr_value(attrs, key, path)
    if (isinstance(value, bool | np.bool_) or not isinstance(value, int | float | np.integer | np.floating)
            or not np.isfinite(value) or float(value) <= 0):
        raise MapFormatError(f"{path}: root attribute {key!r} must be a positive number, found {_show(value)}")
    return float(value)


def _read_metadata(f: h5py.File, path: Path) -> MapMetadata:
    """The root attributes, each checked for its type and range (``docs/MAP_FORMAT.md``)."""
    attrs = f.attrs
    if "schema_version" not in attrs:
        raise MapFormatError(f"{path}: not a ReRadar map (no schema_version attribute)")
    version = _int_attr(attrs, "schema_version", path, 0)
    if version != SCHEMA_VERSION:
        raise MapFormatError(
            f"{path}: map schema_version {version} is not supported (this build reads {SCHEMA_VERSION}); "
            f"rebuild the map with `reradar build-map`"
        )
    missing = [k for k in _ATTR_FIELDS if k not in attrs]
    if missing:
        raise MapFormatError(f"{path}: map is missing root attributes {missing}")
    preset = _str_attr(attrs, "radar_preset", path)
    if preset != UNKNOWN_RADAR_PRESET and preset.lower() not in PRESETS:
        # scans are decoded with the map's preset: an unknown name fails every localization
        raise MapFormatError(f"{path}: radar_preset {preset[:40]!r} is not a known radar preset; use one of "
                             f"{sorted(PRESETS)} (or {UNKNOWN_RADAR_PRESET!r})")

    def s(key: str) -> str:
        return _str_attr(attrs, key, path)

    return MapMetadata(
        model_id=s("model_id"),
        weights_sha256=s("weights_sha256"),
        radar_preset=preset,
        cartesian_width_px=_int_attr(attrs, "cartesian_width_px", path, 1),
        cartesian_resolution_m=_positive_float_attr(attrs, "cartesian_resolution_m", path),
        descriptor_dim=_int_attr(attrs, "descriptor_dim", path, 1, MAX_DESCRIPTOR_DIM),
        local_descriptor_dim=_int_attr(attrs, "local_descriptor_dim", path, 1, MAX_LOCAL_DESCRIPTOR_DIM),
        num_keyframes=_int_attr(attrs, "num_keyframes", path, 0),
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
    value = _str_attr(attrs, "pose_time", path)
    if value not in (POSE_TIME_MID_SWEEP, POSE_TIME_FIRST_AZIMUTH):
        raise MapFormatError(f"{path}: unknown pose_time {value[:40]!r} (expected {POSE_TIME_MID_SWEEP!r})")
    return value


#: A global heap collection (``GCOL``; where HDF5 keeps variable-length strings: the map's text attributes):
#: signature, version 1, 3 reserved zero bytes, then its size (8 bytes); each object inside it has a 16-byte header
#: (index 2, reference count 2, reserved 4, size 8) followed by its data padded to 8 bytes.
_GCOL_SIGNATURE = b"GCOL"
_GCOL_HEADER = struct.Struct("<4sB3sQ")
_GCOL_OBJECT = struct.Struct("<HHIQ")


def _check_global_heaps(path: Path) -> None:
    """Refuse a file holding a damaged global heap collection, before HDF5 parses it: the library (2.0) loops
    forever on an object of size 0 or one overrunning its collection, at 100 % CPU with its lock held, which
    would block every map read of the process. Scans the whole file for collections (~0.7 s per GB), so it runs
    on uploads only (``probe_map``), not at every open of a map the service wrote or was given on disk."""
    with open(path, "rb") as fh:
        size = fh.seek(0, os.SEEK_END)
        if size < _GCOL_HEADER.size:
            return  # h5py refuses it as not HDF5
        with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            pos = mm.find(_GCOL_SIGNATURE)
            while 0 <= pos <= size - _GCOL_HEADER.size:
                _, version, reserved, length = _GCOL_HEADER.unpack_from(mm, pos)
                if version == 1 and reserved == b"\0\0\0":  # else the 4 bytes are data, not a collection
                    end = pos + length
                    if length < _GCOL_HEADER.size or end > size:
                        raise MapFormatError(f"{path}: corrupt map file (global heap at byte {pos} overruns the "
                                             f"file)")
                    p = pos + _GCOL_HEADER.size
                    while p + _GCOL_OBJECT.size <= end:  # HDF5's own walk; a shorter tail is free space
                        index, _, _, obj_size = _GCOL_OBJECT.unpack_from(mm, p)
                        step = _GCOL_OBJECT.size + -(-obj_size // 8) * 8 if index else obj_size
                        if step == 0 or p + step > end:
                            raise MapFormatError(f"{path}: corrupt map file (global heap at byte {pos} is "
                                                 f"damaged)")
                        p += step
                pos = mm.find(_GCOL_SIGNATURE, pos + 1)


def _open_h5(path: Path) -> h5py.File:
    if not path.is_file():
        raise MapFormatError(f"{path}: no such map file")
    try:
        return h5py.File(path, "r")
    except MapFormatError:
        raise
    except _H5_ERRORS as exc:
        raise MapFormatError(f"{path}: not a readable HDF5 map ({_h5_reason(exc, path)})") from exc


def read_metadata(path: str | Path) -> MapMetadata:
    """Read only the root attributes of the map at ``path`` (cheap; validates them, ``_read_metadata``).

    Raises:
        MapFormatError: not a map, a damaged file, or invalid attributes.
    """
    path = Path(path)
    with _open_h5(path) as f:
        try:
            return _read_metadata(f, path)
        except MapFormatError:
            raise
        except _H5_ERRORS as exc:
            raise MapFormatError(f"{path}: corrupt map file ({_h5_reason(exc, path)})") from exc


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
        place_repetition: the keyframes' place repetitions measured at build time (``RepetitionTable``), or None
            for a map built without them (the localizer then measures each keyframe as it first wins), or opened
            with ``read_place_repetition=False`` (a table about to be replaced is not read, so a damaged one can be).
    """

    def __init__(self, path: str | Path, read_place_repetition: bool = True) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self._sha256: str | None = None
        self._file: h5py.File | None = _open_h5(self.path)
        self.global_descriptors: np.ndarray | None
        try:
            _check_links(self._file, self.path)
            self.metadata = _read_metadata(self._file, self.path)
            self.timestamps_us, self.poses, self.global_descriptors = self._read_arrays(self._file)
            try:
                self.dense_settings = self._read_dense_settings(self._file)
            except MapFormatError as exc:  # the images are an optional extra: the keyframes are served without them
                logger.warning("%s; its dense images are not used", exc)
                self.dense_settings = None
            try:
                self.place_repetition = self._read_place_repetition(self._file) if read_place_repetition else None
            except MapFormatError as exc:  # the remedy: measure it again (the keyframes are intact)
                raise MapFormatError(f"{exc}; `reradar map-repetition` measures and stores it again") from exc
        except MapFormatError:
            self.close()
            raise
        except _H5_ERRORS as exc:  # a damaged file: h5py's own errors (e.g. "Link visitation failed")
            self.close()
            raise MapFormatError(f"{self.path}: corrupt map file ({_h5_reason(exc, self.path)})") from exc

    def _read_arrays(self, f: h5py.File) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Timestamps (N,) int64, poses (N, 3) float64 and global descriptors (N, D) float32: each dataset's
        header (shape, dtype, stored size) is checked before it is read, its values after."""
        path, n, d = self.path, self.metadata.num_keyframes, self.metadata.descriptor_dim
        if not isinstance(f.get("keyframes", getlink=True), h5py.HardLink) or not isinstance(f["keyframes"], h5py.Group):
            raise MapFormatError(f"{path}: map has no '/keyframes' group")
        # first, as N sizes everything read below: the groups exist in the file, so N is bounded by its size
        groups = len(f["keyframes"])
        if groups != n:
            raise MapFormatError(f"{path}: {groups} keyframe groups for num_keyframes = {n}")
        ts_ds = _dataset(f, "timestamps_us", path)
        _check_layout(ts_ds, (n,), "iu", "int64 (integer microseconds)", path, f"one per keyframe, num_keyframes = {n}")
        poses_ds = _dataset(f, "poses", path)
        if poses_ds.dtype != np.float64:
            raise MapFormatError(f"{path}: /poses must be float64, found {poses_ds.dtype}")
        _check_layout(poses_ds, (n, 3), "f", "float64", path, f"(x, y, yaw) per keyframe, num_keyframes = {n}")
        g_ds = _dataset(f, "global_descriptors", path)
        _check_layout(g_ds, (n, d), "f", "float32", path, f"num_keyframes = {n} x descriptor_dim = {d}")
        _check_stored(g_ds, path)
        ts = _check_timestamps(np.asarray(ts_ds[()]), path)
        poses = np.asarray(poses_ds[()], dtype=np.float64)
        if not np.all(np.isfinite(poses)):
            raise MapFormatError(f"{path}: /poses contain NaN/inf")
        if np.any(np.abs(poses[:, :2]) > MAX_ABS_COORDINATE_M):
            raise MapFormatError(f"{path}: keyframe poses must lie within +-{MAX_ABS_COORDINATE_M:.0e} m of "
                                 f"the map origin")
        with np.errstate(over="ignore"):  # float64 beyond float32 becomes inf, refused just below
            g = np.ascontiguousarray(g_ds[()], dtype=np.float32)
        _check_global_descriptors(g, path)
        return ts, poses, g

    def _read_dense_settings(self, f: h5py.File) -> str | None:
        """The ``dense_images`` root attribute (text), or None for a map without dense images."""
        if DENSE_IMAGES_ATTR not in f.attrs:
            return None
        return _text_attr(f.attrs, DENSE_IMAGES_ATTR, self.path)

    def read_dense_image(self, index: int) -> np.ndarray:
        """Keyframe ``index``'s dense image (``matching.dense.dense_image`` of its scan in the map's Cartesian
        geometry): (W, W) float32, W = ``metadata.cartesian_width_px``.

        Raises:
            IndexError: ``index`` out of range.
            MapFormatError: the map has no dense images (``dense_settings`` None), the dataset is missing or
                damaged, or the map was closed.
        """
        if not 0 <= index < len(self):
            raise IndexError(f"keyframe {index} out of range [0, {len(self)})")
        if self.dense_settings is None:
            raise MapFormatError(f"{self.path}: the map holds no dense images (build its far view again with "
                                 "`reradar build-map --far-view`)")
        w = self.metadata.cartesian_width_px
        with self._lock:
            if self._file is None:
                raise MapFormatError(f"{self.path}: map is closed")
            try:
                ds = _dataset(self._keyframe_group(index), "dense_image", self.path)
                _check_layout(ds, (w, w), "f", "float16", self.path, f"cartesian_width_px = {w} squared")
                _check_stored(ds, self.path)
                with np.errstate(over="ignore"):
                    img = np.asarray(ds[()], dtype=np.float32)
            except MapFormatError:
                raise
            except _H5_ERRORS as exc:
                raise MapFormatError(
                    f"{self.path}: keyframe {index}'s dense image is damaged ({_h5_reason(exc, self.path)})") from exc
        if not np.isfinite(img).all():
            raise MapFormatError(f"{self.path}: keyframe {index}'s dense image contains NaN/inf")
        return img

    def _read_place_repetition(self, f: h5py.File) -> RepetitionTable | None:
        """The optional ``/place_repetition`` group as a ``RepetitionTable`` (headers checked before data)."""
        if "place_repetition" not in f:
            return None
        path, n = self.path, self.metadata.num_keyframes
        if not isinstance(f.get("place_repetition", getlink=True), h5py.HardLink) or not isinstance(
                f["place_repetition"], h5py.Group):
            raise MapFormatError(f"{path}: '/place_repetition' must be a group")
        grp = f["place_repetition"]
        arrays = {}
        for name, kinds, dtype_name in (("neighbour_score", "f", "a float dtype (float64)"),
                                        ("rival_score", "f", "a float dtype (float64)"),
                                        ("rival_keyframe_id", "iu", "an integer dtype (int64)")):
            ds = _dataset(grp, name, path)
            _check_layout(ds, (n,), kinds, dtype_name, path, f"one per keyframe, num_keyframes = {n}")
            _check_stored(ds, path)
            arrays[name] = np.asarray(ds[()])
        if "settings" not in grp.attrs:
            raise MapFormatError(f"{path}: '/place_repetition' has no 'settings' attribute")
        settings = _text_attr(grp.attrs, "settings", path, "'/place_repetition'")
        try:
            return RepetitionTable(settings, arrays["neighbour_score"].astype(np.float64),
                                   arrays["rival_score"].astype(np.float64),
                                   arrays["rival_keyframe_id"].astype(np.int64))
        except (ConfigError, OverflowError) as exc:
            raise MapFormatError(f"{path}: '/place_repetition': {exc}") from exc

    def __len__(self) -> int:
        return self.metadata.num_keyframes

    def _keyframe_group(self, index: int) -> h5py.Group:
        """The group ``/keyframes/<index:06d>`` of the open file (the caller holds the lock): MapFormatError when it is
        missing, a link or not a group."""
        assert self._file is not None
        kgroup = self._file["keyframes"]
        name = f"{index:06d}"
        if not isinstance(kgroup.get(name, getlink=True), h5py.HardLink):
            raise MapFormatError(f"{self.path}: keyframe {index} is missing or a link")
        grp = kgroup[name]
        if not isinstance(grp, h5py.Group):
            raise MapFormatError(f"{self.path}: keyframe {index}: '/keyframes/{name}' is not a group")
        return grp

    def read_keyframe(self, index: int) -> ScanFeatures:
        """Features of keyframe ``index`` (keypoints in its sensor frame, metres; float16 descriptors).

        Raises:
            IndexError: ``index`` out of range.
            MapFormatError: the keyframe group is damaged or the map was closed.
        """
        if not 0 <= index < len(self):
            raise IndexError(f"keyframe {index} out of range [0, {len(self)})")
        local_dim = self.metadata.local_descriptor_dim
        with self._lock:
            if self._file is None:
                raise MapFormatError(f"{self.path}: map is closed")
            try:
                grp = self._keyframe_group(index)
                kps_ds = _dataset(grp, "keypoints_xy_m", self.path)
                desc_ds = _dataset(grp, "local_descriptors", self.path)
                _check_keyframe_datasets(kps_ds, desc_ds, local_dim, self.path, index)
                with np.errstate(over="ignore"):  # values beyond float16/32 become inf, refused by _check_keyframe
                    kps = np.asarray(kps_ds[()], dtype=np.float32)
                    desc = np.asarray(desc_ds[()], dtype=np.float16)
                if self.global_descriptors is not None:
                    g = self.global_descriptors[index]
                else:  # released after indexing: read the one row from disk (checked at open)
                    g = np.asarray(_dataset(self._file, "global_descriptors", self.path)[index], dtype=np.float32)
            except MapFormatError:
                raise
            except _H5_ERRORS as exc:
                raise MapFormatError(
                    f"{self.path}: keyframe {index} is damaged ({_h5_reason(exc, self.path)})") from exc
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


def open_map(path: str | Path, model_id: str | None = None, weights_sha256: str | None = None,
             read_place_repetition: bool = True) -> KeyframeMap:
    """Open the map at ``path``; if ``weights_sha256`` is given, refuse a map built by another model;
    ``read_place_repetition=False``: leave its ``/place_repetition`` unread (``KeyframeMap``).

    Raises:
        MapFormatError: unreadable / wrong schema / inconsistent file.
        ModelMismatchError: built with other weights.
    """
    kf_map = KeyframeMap(path, read_place_repetition)
    if weights_sha256 is not None:
        try:
            check_model(kf_map.metadata, model_id or "?", weights_sha256, kf_map.path)
        except ModelMismatchError:
            kf_map.close()
            raise
    return kf_map


#: Seconds the child process of ``probe_map`` may take to read a map through (a 512 MB map reads in seconds).
PROBE_TIMEOUT_S = 300.0
#: exit status of the ``probe_map`` child for a map refused with ``MapFormatError`` (its message on stdout)
_PROBE_REFUSED = 3
_PROBE_CODE = "import sys; from maps.store import _probe_main; sys.exit(_probe_main(sys.argv[1]))"


def _probe_main(path: str) -> int:
    """``probe_map``'s child: open the map and read every keyframe; 0 if it passes, ``_PROBE_REFUSED`` (the
    message on stdout) if it is refused."""
    logging.disable(logging.WARNING)  # nobody reads the child's log; a refusal is reported through stdout
    try:
        with KeyframeMap(path) as kf_map:
            for i in range(len(kf_map)):
                kf_map.read_keyframe(i)
    except MapFormatError as exc:
        sys.stdout.write(str(exc))
        return _PROBE_REFUSED
    return 0


def probe_map(path: str | Path, timeout_s: float = PROBE_TIMEOUT_S) -> None:
    """Open the untrusted map at ``path`` and read every keyframe through the checks in a child process, before
    this process touches it (uploads). The HDF5 library is not hardened against crafted files: a damaged variable-
    length string type or heap makes it crash (segfault) or spin forever, which here would take the service
    down; in the child it costs the child (~0.3 s to start one).

    Raises:
        MapFormatError: the map is refused (the child's message), crashed the child, or was not read through within
            ``timeout_s``.
        RuntimeError: the child failed otherwise (it could not start, or a bug); not the map's fault.
    """
    path = Path(path)
    _check_global_heaps(path)  # a heap that makes HDF5 spin is refused at once, not after the child's time limit
    # the child imports this module as the parent did, whichever way that was (installed, source tree, tests)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
    try:
        done = subprocess.run([sys.executable, "-c", _PROBE_CODE, str(path)], capture_output=True, env=env,
                              timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired:
        raise MapFormatError(f"{path}: corrupt map file (not read through within {timeout_s:.0f} s)") from None
    if done.returncode == 0:
        return
    if done.returncode == _PROBE_REFUSED:
        raise MapFormatError(done.stdout.decode(errors="replace").strip() or f"{path}: map refused")
    if done.returncode < 0:  # killed by a signal: the HDF5 library crashed on the file
        raise MapFormatError(f"{path}: corrupt map file (the HDF5 library crashed reading it, signal "
                             f"{-done.returncode})")
    tail = done.stderr.decode(errors="replace").strip().splitlines()[-1:] or ["no output"]
    raise RuntimeError(f"map check process failed with exit status {done.returncode}: {tail[0]}")


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


#: ``os.link`` errors that mean the file system has no hard links (``install_file(exclusive=True)`` then
#: checks and renames instead)
_NO_LINK_ERRNOS = frozenset({errno.EPERM, errno.EXDEV, errno.ENOTSUP, errno.EOPNOTSUPP, errno.ENOSYS})


def install_file(src: str | Path, dst: str | Path, exclusive: bool = False) -> Path:
    """Durably move a complete file into place: fsync ``src``, rename it over ``dst`` (atomic within one
    filesystem), fsync both folders. After a crash ``dst`` is either the old file or the whole new one.

    ``exclusive``: never replace an existing ``dst`` (map files shared by several processes: two writers of
    one map id must not silently overwrite each other): ``src`` is hard-linked as ``dst``, which fails
    atomically when ``dst`` exists, then unlinked. On a file system without hard links the check and the
    rename are two steps (a writer in between can still be overwritten). The installed file keeps ``src``'s
    inode, size and modification time.

    Raises:
        FileExistsError: ``exclusive`` and ``dst`` exists (``src`` is left in place).
    """
    src, dst = Path(src), Path(dst)
    with open(src, "rb+") as fh:
        os.fsync(fh.fileno())
    if exclusive:
        try:
            os.link(src, dst)
        except FileExistsError:
            raise
        except OSError as exc:
            if exc.errno not in _NO_LINK_ERRNOS:
                raise
            logger.warning("%s: no hard links on this file system (%s); installing %s with a check and a rename",
                           dst.parent, exc.strerror, dst.name)
            if dst.exists():
                raise FileExistsError(errno.EEXIST, "file exists", str(dst)) from None
            os.replace(src, dst)
        else:
            os.unlink(src)
    else:
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


def _write_place_repetition(f: h5py.File, table: RepetitionTable, num_keyframes: int) -> None:
    """Write ``table`` as ``/place_repetition`` of the open map ``f`` (replacing one that is there)."""
    if len(table) != num_keyframes:
        raise ValueError(f"place repetition table has {len(table)} rows for {num_keyframes} keyframes")
    if "place_repetition" in f:
        del f["place_repetition"]
    grp = f.create_group("place_repetition")
    grp.create_dataset("neighbour_score", data=np.asarray(table.neighbour_score, np.float64))
    grp.create_dataset("rival_score", data=np.asarray(table.rival_score, np.float64))
    grp.create_dataset("rival_keyframe_id", data=np.asarray(table.rival_keyframe_id, np.int64))
    grp.attrs["settings"] = table.settings


def store_place_repetition(path: str | Path, table: RepetitionTable, out: str | Path | None = None,
                           expect_sha256: str | None = None, overwrite: bool = False) -> Path:
    """Write ``table`` into a copy of the map at ``path`` (replacing a stored one) and install the copy atomically at
    ``out`` (default: over ``path``, or over the file a symbolic link ``path`` names): a map built before its place
    repetition was stored gets it without its scans. The copy keeps the original's permission bits. The original is
    untouched until the finished copy is renamed over it; on any error nothing is installed.

    Args:
        expect_sha256: the SHA-256 of the map the table was measured on: refused if the file at ``path`` is another.
        overwrite: replace an existing ``out`` (``path`` itself is always replaced when ``out`` is None).

    Raises:
        MapFormatError: ``path`` is not a readable map, not the one measured, or was replaced while it was copied.
        FileExistsError: ``out`` exists and not ``overwrite``. ValueError: the table's length is not the map's.
    """
    import shutil

    src = Path(path)
    dst = Path(out) if out is not None else src.resolve()  # a link keeps pointing at the completed map
    if out is not None and dst.exists() and not overwrite:
        raise FileExistsError(errno.EEXIST, "file exists; pass overwrite to replace it", str(dst))
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    compact = tmp.with_name(tmp.name + ".compact")

    def identity(st: os.stat_result) -> tuple[int, int, int, int]:
        return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns

    try:
        before = identity(os.stat(src))
        shutil.copyfile(src, tmp)
        shutil.copymode(src, tmp)
        # the copy is validated as any map is opened (but the table it replaces), and is the one measured
        with KeyframeMap(tmp, read_place_repetition=False) as m:
            n = len(m)
            if expect_sha256 is not None and m.content_sha256() != expect_sha256:
                raise MapFormatError(f"{src}: the map changed while its place repetition was measured; run again")
        with h5py.File(tmp, "r") as f:
            replacing = "place_repetition" in f
        if replacing:  # HDF5 keeps a deleted table's space: a compact copy without it, so a re-run does not grow
            _copy_map_without(tmp, compact, "place_repetition")
            os.replace(compact, tmp)
        with h5py.File(tmp, "r+") as f:
            _write_place_repetition(f, table, n)
        if identity(os.stat(src)) != before:  # replaced meanwhile (e.g. re-registered): never revert it
            raise MapFormatError(f"{src}: the map was replaced while its place repetition was stored; run again")
        install_file(tmp, dst, exclusive=out is not None and not overwrite)
    except BaseException:
        tmp.unlink(missing_ok=True)
        compact.unlink(missing_ok=True)
        raise
    return dst


def _copy_map_without(src: Path, dst: Path, member: str) -> None:
    """Copy the HDF5 map ``src`` to a new file ``dst`` without its top-level ``member``: the root attributes and
    every other object with its attributes and storage settings (``H5Ocopy``), written anew, so the space of the
    member left out is not carried over."""
    import shutil

    with h5py.File(src, "r") as fin, h5py.File(dst, "w") as fout:
        for key, value in fin.attrs.items():
            fout.attrs[key] = value
        for name in fin:
            if name != member:
                fin.copy(fin[name], fout, name=name)
    shutil.copymode(src, dst)


class MapWriter:
    """Streaming, atomic map writer.

    Use as a context manager: ``add`` keyframes in batches, the file appears under ``path`` only when the
    ``with`` block exits without an exception (temporary file + flush + fsync + rename); on error the
    temporary file is deleted and any existing map at ``path`` is left untouched.
    """

    def __init__(self, path: str | Path, metadata: MapMetadata, overwrite: bool = False,
                 dense_settings: str | None = None) -> None:
        """``dense_settings``: every keyframe added carries its dense image (``add(..., dense_image=)``), made with
        these settings (``matching.dense.dense_image_settings``), stored as the root attribute ``dense_images``."""
        self.dense_settings = dense_settings
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
        self._repetition: RepetitionTable | None = None
        self._read_lock = threading.Lock()

    def __enter__(self) -> MapWriter:
        try:  # the OS's reason in words, not HDF5's "unable to synchronously create file" naming the temporary file
            with open(self._tmp, "xb"):
                pass
        except OSError as exc:
            raise OSError(exc.errno, f"cannot create the map file {self.path.name} there: "
                                     f"{exc.strerror or exc}") from None
        try:
            self._file = h5py.File(self._tmp, "w")
        except BaseException:
            self._tmp.unlink(missing_ok=True)
            raise
        self._file.create_group("keyframes")
        return self

    def add(self, features: ScanFeatures, pose: np.ndarray, timestamp_us: int | None = None,
            dense_image: np.ndarray | None = None) -> int:
        """Append one keyframe with its map pose ``T_map_keyframe`` (3,) (x m, y m, yaw rad); returns its id.
        ``dense_image``: (W, W) float, W = ``metadata.cartesian_width_px``, required exactly when the writer was
        made with ``dense_settings`` (stored float16, compressed)."""
        if self._file is None:
            raise RuntimeError("MapWriter.add outside its with-block")
        if (dense_image is None) != (self.dense_settings is None):
            raise ValueError("a map with dense images needs one for every keyframe (and one without takes none)")
        if dense_image is not None:
            w = self.metadata.cartesian_width_px
            dense_image = np.asarray(dense_image, dtype=np.float16)
            if dense_image.shape != (w, w) or not np.isfinite(dense_image).all():
                raise ValueError(f"dense image must be ({w}, {w}) finite values, got shape {dense_image.shape}")
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
        if dense_image is not None:  # ~90 KB per 257 px image (float16 speckle compresses ~1.4:1)
            grp.create_dataset("dense_image", data=dense_image, chunks=dense_image.shape, compression="gzip",
                               compression_opts=4, shuffle=True)
        self._ts.append(int(features.timestamp_us if timestamp_us is None else timestamp_us))
        self._poses.append(pose)
        self._glob.append(g)
        self._n += 1
        return self._n - 1

    def __len__(self) -> int:
        return self._n

    @property
    def poses(self) -> np.ndarray:
        """(n, 3) float64 map poses of the keyframes added so far."""
        return np.asarray(self._poses, dtype=np.float64).reshape(self._n, 3)

    @property
    def timestamps_us(self) -> np.ndarray:
        """(n,) int64 timestamps of the keyframes added so far."""
        return np.asarray(self._ts, dtype=np.int64).reshape(self._n)

    @property
    def global_descriptors(self) -> np.ndarray:
        """(n, D) float32 global descriptors of the keyframes added so far."""
        return np.asarray(self._glob, dtype=np.float32).reshape(self._n, self.metadata.descriptor_dim)

    def read_keyframe(self, index: int) -> ScanFeatures:
        """Keyframe ``index`` as written (float32 keypoints, float16 descriptors: what a reader of the finished map
        gets), read back from the temporary file, so the map's place repetition can be measured on exactly what is
        stored before the map is installed (``maps.build.measure_place_repetition``). Thread-safe."""
        if self._file is None:
            raise RuntimeError("MapWriter.read_keyframe outside its with-block")
        if not 0 <= index < self._n:
            raise IndexError(f"keyframe {index} out of range [0, {self._n})")
        with self._read_lock:
            grp = self._file["keyframes"][f"{index:06d}"]
            kps = np.asarray(grp["keypoints_xy_m"][()], dtype=np.float32)
            desc = np.asarray(grp["local_descriptors"][()], dtype=np.float16)
        return ScanFeatures(self._glob[index], kps, desc, self._ts[index])

    def set_place_repetition(self, table: RepetitionTable) -> None:
        """Store ``table`` (one row per keyframe) as the map's ``/place_repetition`` when the map is finished."""
        if len(table) != self._n:
            raise ValueError(f"place repetition table has {len(table)} rows for {self._n} keyframes")
        self._repetition = table

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
        if self._repetition is not None:
            _write_place_repetition(f, self._repetition, self._n)
        if self.dense_settings is not None:
            f.attrs[DENSE_IMAGES_ATTR] = self.dense_settings
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
