"""Render a traversal to disk in a real dataset layout (Boreas, Oxford or MulRan), resumably."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import shutil
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from reradar_core.errors import ConfigError, ReRadarError
from reradar_core.io.datasets import (
    LAYOUTS,
    SIM_META_FILE,
    read_sequence_meta,
    scan_path,
    write_sequence_meta,
    write_sequence_poses,
)
from reradar_core.io.poses import PoseSequence
from reradar_core.io.presets import get_preset
from reradar_core.io.scan import encode_navtech_png_bytes
from reradar_core.sim.sensor import SensorConfig, render_scan, scan_seed
from reradar_core.sim.traversal import Traversal

__all__ = ["COMPLETE_MARKER", "SIM_VERSION", "carry_over", "pose_track", "render_key", "render_sequence", "is_complete"]

logger = logging.getLogger(__name__)

#: Written last into a sequence folder once every scan and the pose file are on disk.
COMPLETE_MARKER = ".reradar_complete"
#: Bumped whenever the world or sensor model changes what is rendered: cached sequences rendered by another
#: version are re-rendered instead of being reused.
SIM_VERSION = "11"
_STARTED = ".reradar_render_version"


def is_complete(root: str | Path) -> bool:
    """True when ``root`` holds a finished render made by this simulator version."""
    marker = Path(root) / COMPLETE_MARKER
    return marker.is_file() and marker.read_text().split()[:1] == [SIM_VERSION]


def _link_or_copy(src: str, dst: str) -> None:
    """Hard link ``src`` at ``dst``; a plain copy where the file system cannot link (another device)."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def carry_over(src: Path, dst: Path, old_version: str) -> bool:
    """Take a render of an earlier simulator version over as this version's, without rendering it again.

    For a sequence that this version renders byte-identically (``benchmarks/verify_sim_identity.py`` checks it):
    the complete folder ``src`` (made by ``old_version``) is copied to ``dst`` as hard links (no extra disk; a
    plain copy across file systems), then its completion marker, render-version file and ``reradar_sim.json``
    are written anew in ``dst`` as new files, so ``src`` keeps its own; the JSON gets a ``carried_over_from``
    note. The marker is written last.

    Returns:
        True when carried over; False (nothing changed) when ``src`` is not a complete render of
        ``old_version`` or ``dst`` already is a complete render of this version.
    """
    marker = src / COMPLETE_MARKER
    if not marker.is_file() or marker.read_text().split()[:1] != [old_version] or is_complete(dst):
        return False
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst, copy_function=_link_or_copy)
    count = marker.read_text().split()[1:]
    # every rewrite renames a new file over the link (``_write_atomic``), so ``src`` keeps its own files
    meta = read_sequence_meta(dst)
    if meta:
        meta["sim_version"] = SIM_VERSION
        meta["carried_over_from"] = f"{old_version} (byte-identical render, benchmarks/verify_sim_identity.py)"
        _write_atomic(dst / SIM_META_FILE, json.dumps(meta, indent=2, sort_keys=True).encode())
    _write_atomic(dst / _STARTED, f"{SIM_VERSION}\n".encode())
    _write_atomic(dst / COMPLETE_MARKER, (" ".join([SIM_VERSION, *count]) + "\n").encode())  # last: complete
    return True


#: What the simulator writes into a sequence folder, in any layout (relative paths): the metadata, the pose files and
#: (``_SCAN_DIRS``) the scans. Nothing else is ever removed from an output folder.
_WRITTEN_FILES = frozenset({SIM_META_FILE, COMPLETE_MARKER, _STARTED, "applanix/radar_poses.csv",
                            "gt/radar_odometry.csv", "global_pose.csv"})
_SCAN_DIRS = ("radar", "sensor_data/radar/polar")
_SCAN_NAME = re.compile(r"\d+\.png")
_TEMP_NAME = re.compile(r"\..+\.\d+\.tmp")  # ``_write_atomic``'s, left by an interrupted render


def _written_by_simulator(out: Path, f: Path) -> bool:
    rel = f.relative_to(out)
    parent = rel.parent.as_posix()
    return (rel.as_posix() in _WRITTEN_FILES or (parent in _SCAN_DIRS and _SCAN_NAME.fullmatch(rel.name) is not None)
            or (parent in (".", "applanix", "gt", *_SCAN_DIRS) and _TEMP_NAME.fullmatch(rel.name) is not None))


def render_key(traversal: Traversal, trajectory: PoseSequence, times_us: np.ndarray, scan_indices: np.ndarray,
               preset: str, layout: str, config: SensorConfig) -> str:
    """A digest of everything that decides a render's scans: simulator version, preset and layout, the world (seed,
    profile, roads), the traversal (seed, condition, traffic), the driven trajectory (lateral offset included), the
    selected scan times and their indices, and the sensor model. Equal keys render byte-identical folders."""
    h = hashlib.sha256()
    for part in (SIM_VERSION, preset, layout):
        h.update(f"{part}\n".encode())
    traversal.add_to_digest(h)
    h.update(f"{config!r}\n".encode())
    for arr in (trajectory.timestamps_us, trajectory.xy, trajectory.yaw, times_us, scan_indices):
        a = np.ascontiguousarray(arr)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:32]


def _recorded_key(out: Path) -> str | None:
    """The render key an earlier render of this simulator version recorded in ``out`` (None: none recorded)."""
    started = out / _STARTED
    words = started.read_text().split() if started.is_file() else []
    return words[1] if len(words) == 2 and words[0] == SIM_VERSION else None


def _differences(out: Path, info: dict) -> str:
    """The recorded parameters of ``out``'s earlier render that differ from ``info``, for a message."""
    try:
        old = read_sequence_meta(out)
    except ReRadarError:
        old = {}
    diff = [f"{k} {old[k]} -> {info[k]}" for k in ("sim_version", "preset", "layout", "profile", "world_seed",
                                                   "traversal_seed", "condition", "num_scans")
            if k in old and old[k] != info[k]]
    return ", ".join(diff) or "its trajectory, lateral offset, scan selection or sensor model differ"


def _prepare_folder(out: Path, key: str, info: dict, replace: bool) -> None:
    """Make ``out`` ready for the render ``key``: resume a render of the same key; clear a render of other
    parameters (``replace``) or refuse it; refuse a folder that holds anything but a simulator render."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out} is a file, not a folder; give a new or empty folder as the output")
    out.mkdir(parents=True, exist_ok=True)
    files = [f for f in out.rglob("*") if not f.is_dir()]
    if files:
        foreign = [f.relative_to(out).as_posix() for f in files if not _written_by_simulator(out, f)]
        is_render = (out / _STARTED).is_file() or (out / SIM_META_FILE).is_file()
        if foreign or not is_render:
            shown = foreign or [f.relative_to(out).as_posix() for f in files]
            raise ConfigError(
                f"{out} holds files that are not a simulator render ({', '.join(sorted(shown)[:3])}"
                f"{', ...' if len(shown) > 3 else ''}); give a new or empty folder as the output")
        if _recorded_key(out) != key:
            if not replace:
                raise ConfigError(f"{out} already holds a simulator render with other parameters ("
                                  f"{_differences(out, info)}); pass --overwrite to replace it, or give another "
                                  "output folder")
            logger.info("%s: removing %d files of an earlier render with other parameters", out, len(files))
            for f in files:
                f.unlink()
            for d in ("radar", "sensor_data/radar/polar", "sensor_data/radar", "sensor_data", "applanix", "gt"):
                if (out / d).is_dir() and not any((out / d).iterdir()):
                    (out / d).rmdir()
    _write_atomic(out / _STARTED, f"{SIM_VERSION} {key}\n".encode())


def _write_atomic(path: Path, data: bytes) -> None:
    """Write via a temporary file + rename, so an interrupted render never leaves a truncated scan that a
    resumed render would skip."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def pose_track(trajectory: PoseSequence, times_us: np.ndarray, sweep_period_s: float) -> PoseSequence:
    """The poses a sequence's pose file holds: one at every scan start time ``times_us`` (N,) plus every pose
    of ``trajectory`` from the first scan's start to the end of the last sweep (simulator v10).

    Real pose files hold the vehicle's poses at least at every scan the sensor took, and readers interpolate
    them at any other time: the mid-sweep time that keyframe poses and pose ground truth refer to
    (``Sequence.mid_sweep_poses``). A render of every n-th scan that wrote only its own scans' poses (v1-v9) left
    0.75-2 s between rows, and at a corner a linear interpolation over that gap put the mid-sweep heading up to
    6 degrees off the drive's (docs/SIMULATOR.md, "Simulator v10").
    """
    t = np.asarray(times_us, dtype=np.int64)
    tr = trajectory.timestamps_us
    end = int(t[-1]) + int(round(sweep_period_s * 1e6))
    inner = tr[(tr > t[0]) & (tr <= end)]
    stamps = np.union1d(t, inner)
    poses = trajectory.interpolate(stamps)
    return PoseSequence(stamps, poses[:, :2], poses[:, 2])


def render_sequence(out_dir: str | Path, traversal: Traversal, trajectory: PoseSequence, times_us: np.ndarray,
                    scan_indices: np.ndarray | None = None, preset: str = "boreas", layout: str | None = None,
                    config: SensorConfig = SensorConfig(), progress: bool = True, meta: dict | None = None,
                    desc: str | None = None, replace: bool = False) -> Path:
    """Render one scan per start time in ``times_us`` into ``out_dir`` and write the layout's pose file.

    Args:
        out_dir: sequence folder (created).
        traversal: world + traversal state.
        trajectory: T_world_sensor poses (interpolated per azimuth).
        times_us: (N,) scan start times (first azimuth), microseconds.
        scan_indices: (N,) index of each scan in the traversal's full scan list; seeds each scan's noise so
            a scan renders identically whatever ``every``/``limit`` selected it. Defaults to 0..N-1.
        preset: radar preset name.
        layout: ``boreas``, ``oxford`` or ``mulran``; defaults to the preset's layout.
        config: sensor model.
        progress: show a tqdm bar.
        meta: extra provenance written into ``reradar_sim.json``.
        desc: progress bar label.
        replace: when ``out_dir`` holds a render with other parameters (another ``render_key``), remove its files
            (only those the simulator writes) instead of refusing it.

    Returns:
        ``out_dir``. A render of the same ``render_key`` already there is resumed: its scans are kept, scans outside
        the selection removed. The completion marker is written last.

    Raises:
        ConfigError: ``out_dir`` is a file, holds files the simulator does not write (never removed), or holds a
        render with other parameters and ``replace`` is False.
    """
    p = get_preset(preset)
    layout = layout or p.dataset_layout
    if layout not in LAYOUTS:
        raise ConfigError(f"unknown dataset layout {layout!r}; choose one of {LAYOUTS}")
    out = Path(out_dir)
    times_us = np.asarray(times_us, dtype=np.int64)
    if len(times_us) == 0:
        raise ConfigError(f"{out}: no scan times to render (trajectory too short for every/limit?)")
    idx = np.arange(len(times_us)) if scan_indices is None else np.asarray(scan_indices, dtype=np.int64)
    key = render_key(traversal, trajectory, times_us, idx, p.name, layout, config)
    info = {
        "preset": p.name,
        "layout": layout,
        "num_scans": int(len(times_us)),
        "world_seed": traversal.world.seed,
        "profile": traversal.world.profile.name,
        "traversal_seed": traversal.seed,
        "condition": traversal.condition.name,
        "sim_version": SIM_VERSION,
        "render_key": key,
    }
    _prepare_folder(out, key, info, replace)
    marker = out / COMPLETE_MARKER
    if marker.exists():
        marker.unlink()
    wanted = {scan_path(out, layout, int(t0)) for t0 in times_us}
    for d in _SCAN_DIRS:  # a resumed render keeps only its own selection
        for f in (out / d).glob("*.png") if (out / d).is_dir() else ():
            if f not in wanted and _SCAN_NAME.fullmatch(f.name):
                f.unlink()
    t_start = time.perf_counter()
    rendered = 0
    bar = tqdm(list(zip(times_us, idx, strict=True)), desc=desc or out.name, unit="scan", disable=not progress)
    for t0, k in bar:
        if scan_path(out, layout, int(t0)).is_file():
            continue
        scan = render_scan(traversal, trajectory, int(t0), p, scan_seed(traversal.seed, int(k)), config)
        _write_atomic(scan_path(out, layout, int(t0)), encode_navtech_png_bytes(scan))
        rendered += 1
    track = pose_track(trajectory, times_us, p.sweep_period_s)
    write_sequence_poses(out, layout, track)
    info["oxford_T_world_origin"] = [float(v) for v in track.poses[0]]  # the first scan's pose
    info.update(meta or {})
    write_sequence_meta(out, info)
    marker.write_text(f"{SIM_VERSION} {len(times_us)}\n")
    dt = time.perf_counter() - t_start
    if rendered:
        logger.info("%s: rendered %d scans in %.1f s (%.0f ms/scan)", out, rendered, dt, 1e3 * dt / rendered)
    return out
