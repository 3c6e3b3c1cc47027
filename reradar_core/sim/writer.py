"""Render a traversal to disk in a real dataset layout (Boreas, Oxford or MulRan), resumably."""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from reradar_core.errors import ConfigError
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

__all__ = ["COMPLETE_MARKER", "SIM_VERSION", "carry_over", "pose_track", "render_sequence", "is_complete"]

logger = logging.getLogger(__name__)

#: Written last into a sequence folder once every scan and the pose file are on disk.
COMPLETE_MARKER = ".reradar_complete"
#: Bumped whenever the world or sensor model changes what is rendered: cached sequences rendered by another
#: version are re-rendered instead of being reused.
SIM_VERSION = "10"
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


def _clear_stale(out: Path, layout: str) -> None:
    """Remove scans a different simulator version left in ``out`` (only the layout's scan PNGs)."""
    started = out / _STARTED
    if started.is_file() and started.read_text().strip() == SIM_VERSION:
        return
    scan_dir = scan_path(out, layout, 0).parent
    stale = list(scan_dir.glob("*.png")) if scan_dir.is_dir() else []
    if stale:
        logger.info("%s: removing %d scans rendered by another simulator version", out, len(stale))
    for f in stale:
        f.unlink()
    started.write_text(SIM_VERSION + "\n")


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
                    desc: str | None = None) -> Path:
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

    Returns:
        ``out_dir``. Scans already on disk are kept (resume); the completion marker is written last.
    """
    p = get_preset(preset)
    layout = layout or p.dataset_layout
    if layout not in LAYOUTS:
        raise ConfigError(f"unknown dataset layout {layout!r}; choose one of {LAYOUTS}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    times_us = np.asarray(times_us, dtype=np.int64)
    if len(times_us) == 0:
        raise ConfigError(f"{out}: no scan times to render (trajectory too short for every/limit?)")
    idx = np.arange(len(times_us)) if scan_indices is None else np.asarray(scan_indices, dtype=np.int64)
    marker = out / COMPLETE_MARKER
    if marker.exists():
        marker.unlink()
    _clear_stale(out, layout)
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
    info = {
        "preset": p.name,
        "layout": layout,
        "num_scans": int(len(times_us)),
        "world_seed": traversal.world.seed,
        "profile": traversal.world.profile.name,
        "traversal_seed": traversal.seed,
        "condition": traversal.condition.name,
        "sim_version": SIM_VERSION,
        "oxford_T_world_origin": [float(v) for v in track.poses[0]],  # the first scan's pose
    }
    info.update(meta or {})
    write_sequence_meta(out, info)
    marker.write_text(f"{SIM_VERSION} {len(times_us)}\n")
    dt = time.perf_counter() - t_start
    if rendered:
        logger.info("%s: rendered %d scans in %.1f s (%.0f ms/scan)", out, rendered, dt, 1e3 * dt / rendered)
    return out
