"""Radar sequences on disk in the real dataset layouts: one reader (``load_sequence``) and matching writers.

Layouts (``<seq>`` is the sequence folder):

==========  ==========================================  =================================================
layout      scans                                       poses
==========  ==========================================  =================================================
``boreas``  ``<seq>/radar/<t_us>.png``                  ``<seq>/applanix/radar_poses.csv`` (absolute,
                                                        GPSTime in ns or us; interpolated at each scan)
``oxford``  ``<seq>/radar/<t_us>.png``                  ``<seq>/gt/radar_odometry.csv`` (or
                                                        ``<seq>/radar_odometry.csv``): relative odometry,
                                                        integrated from the first scan (identity pose)
``mulran``  ``<seq>/sensor_data/radar/polar/<t_ns>.png``  ``<seq>/global_pose.csv`` (absolute, t in ns,
                                                        3x4 [R|t]; interpolated at each scan)
==========  ==========================================  =================================================

File names are the scan timestamp = the first azimuth's time (microseconds; nanoseconds for MulRan), as in
Oxford (real Radar RobotCar scans: name = row 0's time, to the microsecond) and our simulator.
Poses are looked up by that name, while a scan's own time (by which a map keys its keyframe) is its first
azimuth's timestamp in the PNG (columns 0-7 of row 0), so ``load_sequence`` refuses a scan whose name and embedded
time lie more than one sweep period apart (``check_scan_name_times``): a scan copied or renamed to another time
would otherwise get the pose of one instant and the time of another.

Oxford odometry: each row ``source_timestamp,destination_timestamp,x,y,z,roll,pitch,yaw,
source_radar_timestamp,destination_radar_timestamp`` is the pose of the source scan in the destination
scan's frame, T_dst_src, in the Oxford RobotCar vehicle frame (x forward, y right, z down, yaw clockwise).
We convert to this project's frame (x forward, y left, yaw counter-clockwise; docs/CONVENTIONS.md) by
negating y and yaw. Integrated Oxford poses are relative to the first scan of the odometry chain, not a map
frame.

Simulated sequences also carry ``<seq>/reradar_sim.json`` (preset name and provenance); real readers ignore it
and ``load_sequence`` uses its preset when none is given.
"""

from __future__ import annotations

import csv
import json
import logging
import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from reradar_core.errors import DatasetError, PoseFileError, ScanFormatError
from reradar_core.geometry.se2 import compose, inverse
from reradar_core.io.poses import (
    PoseSequence,
    gps_offset_hint,
    read_boreas_radar_poses,
    read_mulran_global_pose,
    write_boreas_radar_poses,
    write_mulran_global_pose,
)
from reradar_core.io.presets import PRESETS, RadarPreset, get_preset, mid_sweep_times_us
from reradar_core.io.scan import (
    RadarScan,
    navtech_png_first_time_us,
    preset_bin_sizes,
    read_navtech_png,
    write_navtech_png,
)

__all__ = [
    "LAYOUTS",
    "Sequence",
    "detect_layout",
    "load_sequence",
    "check_pose_span",
    "pose_file_reader",
    "check_pose_time_unit",
    "check_pose_speed",
    "check_pose_steps",
    "MAX_PLAUSIBLE_SPEED_M_S",
    "check_scan_name_times",
    "first_confirmed_problem",
    "warn_names_off_first_azimuth",
    "scan_name_time_mismatch",
    "likely_time_unit",
    "range_grid_difference",
    "POSE_SPAN_SLACK_US",
    "POSE_GAP_MAX_US",
    "mid_sweep_poses_in",
    "scan_path",
    "write_sequence_poses",
    "write_sequence_scan",
    "write_sequence_meta",
    "read_sequence_meta",
    "layout_presets_ambiguous",
    "read_oxford_odometry",
    "write_oxford_odometry",
    "SIM_META_FILE",
]

logger = logging.getLogger(__name__)

LAYOUTS = ("boreas", "oxford", "mulran")
SIM_META_FILE = "reradar_sim.json"
_DEFAULT_PRESET = {"boreas": "boreas", "oxford": "oxford", "mulran": "mulran"}
OXFORD_ODOMETRY_COLUMNS = (
    "source_timestamp,destination_timestamp,x,y,z,roll,pitch,yaw,source_radar_timestamp,"
    "destination_radar_timestamp"
).split(",")


@dataclass
class Sequence:
    """One radar traversal on disk.

    Attributes:
        name: sequence name (the folder name).
        preset: radar preset (range resolution, bins) used to read the scans.
        layout: ``boreas``, ``oxford`` or ``mulran``.
        scan_paths: scan PNG files sorted by timestamp.
        timestamps_us: (N,) int64 scan timestamps (first azimuth), microseconds.
        poses: one pose per scan, T_world_sensor (x, y, yaw) at the scan timestamp, metres / radians.
        root: the sequence folder.
        track: the pose file's whole trajectory (sorted), kept when the sequence is subset, so that poses at
            other times (``mid_sweep_poses``) interpolate the file and not the kept scans; None: ``poses``.
    """

    name: str
    preset: RadarPreset
    layout: str
    scan_paths: list[Path]
    timestamps_us: np.ndarray
    poses: PoseSequence
    root: Path = field(default_factory=Path)
    track: PoseSequence | None = None

    def __len__(self) -> int:
        return len(self.scan_paths)

    def mid_sweep_poses(self) -> np.ndarray:
        """(N, 3) float64 T_world_sensor at each scan's mid-sweep time (``mid_sweep_times_us``).

        A scanning radar turns once while the vehicle moves (4 Hz: 2.5 m at 10 m/s), so a registration of two
        whole sweeps aligns their mid-sweep poses, not their first-azimuth poses: keyframe poses and pose
        ground truth are taken at mid-sweep (docs/CONVENTIONS.md). Interpolated in the pose file's trajectory
        (linear; up to ``POSE_SPAN_SLACK_US`` beyond its ends, where scans are accepted, its end steps continued:
        a pose file ending at the last scan's timestamp held that scan's mid-sweep pose ~1 m back, QA session 24).
        """
        track = self.track if self.track is not None and len(self.track) else self.poses
        return mid_sweep_poses_in(track, self.timestamps_us, self.preset)

    def load_scan(self, i: int) -> RadarScan:
        """Read scan ``i`` (Navtech PNG) with this sequence's preset.

        Raises:
            ScanFormatError: an unreadable scan. DatasetError: its first azimuth's time lies more than one sweep
                from the time its file name gives (``scan_name_time_mismatch``; ``load_sequence`` checks every
                scan up front, this catches a file changed since or one whose time it could not read cheaply).
        """
        path = Path(self.scan_paths[i])
        scan = read_navtech_png(path, self.preset)
        problem = scan_name_time_mismatch(path.name, int(self.timestamps_us[i]), scan.timestamp_us, self.preset,
                                          self.layout)
        if problem:
            raise DatasetError(f"{path.parent}: {problem}")
        return scan

    def subset(self, index: np.ndarray | slice | list[int]) -> Sequence:
        """A sequence holding only the scans at ``index`` (e.g. ``slice(None, None, 5)`` for every 5th)."""
        idx = np.asarray(np.arange(len(self))[index], dtype=np.int64).reshape(-1)  # slices, int or bool masks
        return Sequence(self.name, self.preset, self.layout, [self.scan_paths[i] for i in idx],
                        self.timestamps_us[idx], self.poses.subset(idx), self.root,
                        self.track if self.track is not None else self.poses)


def _scan_dir(root: Path, layout: str) -> Path:
    return root / "sensor_data" / "radar" / "polar" if layout == "mulran" else root / "radar"


def detect_layout(path: str | Path) -> str:
    """Guess the layout of sequence folder ``path`` from its structure.

    Raises:
        DatasetError: the folder does not exist or matches none of the layouts.
    """
    root = Path(path)
    if root.is_file():  # e.g. --dataset SEQ/applanix/radar_poses.csv
        raise DatasetError(f"{root}: is a file; give the sequence folder (the one holding radar/ or sensor_data/)")
    if not root.is_dir():
        raise DatasetError(f"{root}: sequence folder does not exist")
    mulran = (root / "sensor_data" / "radar" / "polar").is_dir()
    if mulran and (root / "radar").is_dir():
        # a stray MulRan scan folder beside a Boreas / Oxford one was taken for the sequence: a 1-keyframe map
        raise DatasetError(f"{root}: holds scans in two layouts (radar/ for Boreas or Oxford, sensor_data/radar/"
                           "polar/ for MulRan); name the one to read (--layout boreas|oxford|mulran) or move the "
                           "other out")
    if mulran:
        return "mulran"
    if (root / "radar").is_dir():
        if (root / "applanix" / "radar_poses.csv").is_file():
            return "boreas"
        if (root / "gt" / "radar_odometry.csv").is_file() or (root / "radar_odometry.csv").is_file():
            return "oxford"
        raise DatasetError(
            f"{root}: has radar/ but no poses: expected applanix/radar_poses.csv (Boreas) or "
            "gt/radar_odometry.csv (Oxford)"
        )
    raise DatasetError(
        f"{root}: not a radar sequence: expected radar/*.png (Boreas/Oxford) or sensor_data/radar/polar/*.png "
        "(MulRan)"
    )


def scan_path(root: str | Path, layout: str, timestamp_us: int) -> Path:
    """Where the scan with first-azimuth time ``timestamp_us`` lives in ``layout`` under ``root``."""
    root = Path(root)
    if layout == "mulran":
        return _scan_dir(root, layout) / f"{int(timestamp_us) * 1000}.png"
    if layout in ("boreas", "oxford"):
        return _scan_dir(root, layout) / f"{int(timestamp_us)}.png"
    raise DatasetError(f"unknown dataset layout {layout!r}; choose one of {LAYOUTS}")


def _list_scans(root: Path, layout: str) -> tuple[list[Path], np.ndarray]:
    folder = _scan_dir(root, layout)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: no scan folder (scan PNGs named <timestamp>.png)")
    paths = []
    stamps = []
    # the suffix in any case: a scan renamed to .PNG was left out of the map without a word (QA session 38)
    for p in (q for q in folder.iterdir() if q.suffix.lower() == ".png"):  # a folder so named is refused later
        try:
            t = int(p.stem)
        except ValueError:
            logger.warning("%s: skipping file whose name is not a timestamp", p)
            continue
        paths.append(p)
        stamps.append(t // 1000 if layout == "mulran" else t)
    if not paths:
        raise DatasetError(f"{folder}: no scan PNGs named <timestamp>.png")
    order = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
    paths, times = [paths[i] for i in order], np.asarray(stamps, dtype=np.int64)[order]
    same = np.flatnonzero(np.diff(times) == 0)
    if len(same):  # e.g. 001000000.png beside 1000000.png: one pose, and a map keys keyframes by time
        a, b = paths[int(same[0])].name, paths[int(same[0]) + 1].name
        unit = " (MulRan names are nanoseconds, read to the microsecond)" if layout == "mulran" else ""
        raise DatasetError(f"{folder}: scans {a} and {b} are named by one time, {int(times[same[0]])} us{unit}; "
                           "keep one of them")
    return paths, times


def scan_name_time_mismatch(name: str, name_time_us: int, embedded_us: int, preset: RadarPreset,
                            layout: str = "oxford") -> str | None:
    """Why scan file ``name`` (basename) cannot be used, when the time its name gives (``name_time_us``, µs) and
    the time it carries (``embedded_us``: its first azimuth's, columns 0-7 of row 0) lie more than one sweep
    period of ``preset`` apart; None when they agree within it.

    The name keys the scan's pose (pose files are looked up or interpolated at it), the embedded time is the
    scan's own (``RadarScan.timestamp_us``: a map's keyframe time, a service answer's ``timestamp_us``). A name
    is normally the first azimuth's time (Oxford, our simulator) and any azimuth of the sweep is within one
    period of it, so a dataset naming its scans by another azimuth's time still loads; a larger difference is
    another instant (a scan copied or renamed to another time, or a wrong clock), never a naming convention.
    """
    period_us = int(round(preset.sweep_period_s * 1e6))
    diff = int(name_time_us) - int(embedded_us)
    if abs(diff) <= period_us:
        return None
    unit = " (MulRan names are nanoseconds)" if layout == "mulran" else ""
    rename = scan_path(Path(), layout, int(embedded_us)).name if layout in LAYOUTS else f"{int(embedded_us)}.png"
    ratio = int(name_time_us) / int(embedded_us) if int(embedded_us) > 0 else 0.0
    if 0.999e3 < ratio < 1.001e3:  # a whole folder named in another unit: say so, not "rename each scan"
        return (f"scan {name}: its file name gives the time {int(name_time_us)} us, 1000 times the time the scan "
                f"carries ({int(embedded_us)} us, columns 0-7, first azimuth): the names look like nanoseconds. "
                + ("Name the scans by their time in microseconds, or read the folder in the MulRan layout, whose "
                   "names are nanoseconds" if layout != "mulran" else "Check the scans' own timestamps"))
    if 0.999e-3 < ratio < 1.001e-3:
        return (f"scan {name}: its file name gives the time {int(name_time_us)} us{unit}, 1/1000 of the time the "
                f"scan carries ({int(embedded_us)} us, columns 0-7, first azimuth): the names look like "
                + ("microseconds where this layout names scans in nanoseconds; rename them to nanoseconds "
                   f"({rename}) or read the folder in a layout named in microseconds (oxford, boreas)"
                   if layout == "mulran" else "milliseconds; name the scans by their time in microseconds"))
    return (f"scan {name}: its file name gives the time {int(name_time_us)} us{unit}, but the timestamps in the "
            f"scan (columns 0-7, first azimuth) say {int(embedded_us)} us, {abs(diff) / 1e6:.6g} s "
            f"{'earlier' if diff > 0 else 'later'}: more than one sweep ({preset.sweep_period_s:g} s), so its pose "
            f"(taken at the file name's time) and its time (the embedded one, which a map keys its keyframe by) "
            f"would be two different instants. If the scan's timestamps are right, rename it to {rename} (its "
            f"pose is then taken at that time); if it is a copy of another scan, or you cannot tell which time is "
            f"right, remove it from the folder")


def check_scan_name_times(paths: list[Path], name_times_us: np.ndarray, preset: RadarPreset,
                          layout: str = "oxford") -> None:
    """Refuse scans whose file-name time and embedded first-azimuth time lie more than one sweep period apart
    (``scan_name_time_mismatch``), before any scan is used.

    Each PNG's embedded time is read from its first row (``navtech_png_first_time_us``: a few small reads, no
    decode). A scan is decoded (``read_navtech_png``) only when that read fails (an interlaced PNG, say) or to
    confirm the first disagreement: a file the reader refuses (another layout, whose first pixels are no time;
    a corrupt one) is left to it, which says what is wrong when the scan is read. Names more than one azimuth
    interval off (within a sweep) load, with one warning: the poses assume the name is the first azimuth's time
    (docs/CONVENTIONS.md).

    Args:
        paths: the scan files. name_times_us: (N,) int64, the times their names give, µs. preset: the radar the
            folder is read with (its sweep period is the tolerance). layout: for the message (MulRan: ns names).

    Raises:
        DatasetError: naming the folder and the first such scan, both times, how many scans disagree, and what to
            do; or two scans that carry one time (a copy: ``_refuse_a_copy``).
    """
    off_us: list[int] = []
    carried: dict[int, Path] = {}
    folder = Path(paths[0]).parent if paths else Path()

    def flagged() -> Iterator[Callable[[], str | None]]:
        for path, t_name in zip(paths, np.asarray(name_times_us, np.int64).tolist(), strict=True):
            path = Path(path)
            t0 = navtech_png_first_time_us(path)
            confirmed = t0 is None
            if t0 is None:
                t0 = _decoded_first_time_us(path, preset)
            if t0 is None:
                continue
            _refuse_a_copy(carried, path, t0, preset, folder)
            problem = scan_name_time_mismatch(path.name, t_name, t0, preset, layout)
            if problem is None:
                if t_name != t0:
                    off_us.append(t_name - t0)
                continue

            def decoded(path: Path = path, t_name: int = t_name, problem: str = problem,
                        confirmed: bool = confirmed) -> str | None:
                if confirmed:  # the quick read failed: this is already the decoded time's verdict
                    return problem
                # the first pixels of a scan of another layout are no time: the reader's decode has the last word
                t = _decoded_first_time_us(path, preset)
                return None if t is None else scan_name_time_mismatch(path.name, t_name, t, preset, layout)

            yield decoded

    first, disagree = first_confirmed_problem(flagged())
    if first is not None:
        more = f" ({disagree} of {len(paths)} scans disagree so; the first is named)" if disagree > 1 else ""
        raise DatasetError(f"{folder}: {first}{more}")
    warn_names_off_first_azimuth(off_us, len(paths), preset, logger)


def warn_names_off_first_azimuth(off_us: list[int], total: int, preset: RadarPreset, log: logging.Logger,
                                 what: str = "scans") -> None:
    """Log one warning when scans are named by a time more than one azimuth interval of ``preset`` from their first
    azimuth's (``off_us``: name minus embedded time, µs, of the scans within a sweep of it; ``total``: all scans):
    a naming convention, not another instant, but poses are taken at the names' times and mid-sweep poses half a
    sweep after them, which assumes the first azimuth's (docs/CONVENTIONS.md)."""
    step_us = preset.sweep_period_s * 1e6 / preset.num_azimuths
    beyond = [d for d in off_us if abs(d) > step_us]
    if beyond:
        log.warning("%d of %d %s are named by a time up to %+.1f ms from their first azimuth's time: poses are "
                    "taken at the names' times and mid-sweep poses half a sweep after them, which assumes the names "
                    "are the first azimuth's time (docs/CONVENTIONS.md)", len(beyond), total, what,
                    max(beyond, key=abs) / 1e3)


def _refuse_a_copy(carried: dict[int, Path], path: Path, t_us: int, preset: RadarPreset, folder: Path) -> None:
    """Refuse scan ``path`` when an earlier scan of the folder carries the same time ``t_us`` (µs, its first
    azimuth's; ``carried``: time -> scan, filled here): a map keys its keyframes by it, so the built map would be
    unreadable (a copy named within a sweep of its time passes the name check). Both scans are decoded first: the
    first pixels of a file the reader refuses are no time, and the reader then says what is wrong with it."""
    other = carried.setdefault(int(t_us), path)
    if other == path:
        return
    if _decoded_first_time_us(path, preset) != t_us or _decoded_first_time_us(other, preset) != t_us:
        return
    raise DatasetError(f"{folder}: scans {other.name} and {path.name} carry the same scan time, {int(t_us)} us "
                       "(columns 0-7 of their first row): one is a copy of the other, and a map keys its keyframes by "
                       "this time; remove the copy")


def first_confirmed_problem(flagged: Iterable[Callable[[], str | None]]) -> tuple[str | None, int]:
    """The first problem a cheap check found that its full check upholds, and how many were found from it on.

    Args:
        flagged: one callable per item the cheap check flagged, in order: the full check's verdict on that item,
            the problem to report (None: it does not uphold the cheap check's, e.g. the decoder refuses the file,
            which then says why when it is read); called only until one upholds it, so that at most one flagged
            item is decoded.

    Returns:
        The first upheld problem (None when none is) and the number of items flagged from that one on (later items
        are counted on the cheap check's word).
    """
    first: str | None = None
    count = 0
    for confirm in flagged:
        if first is None:
            upheld = confirm()
            if upheld is None:
                continue
            first = upheld
        count += 1
    return first, count


def _decoded_first_time_us(path: Path, preset: RadarPreset) -> int | None:
    """The first azimuth's time of scan ``path`` read as the sequence reads it (``read_navtech_png``); None when
    the reader refuses it (it does so again, saying why, when the scan is read)."""
    try:
        return read_navtech_png(path, preset).timestamp_us
    except ScanFormatError:
        return None


#: The largest heading change an Oxford odometry row may hold (between two consecutive scans), radians.
_MAX_FRAME_TURN_RAD = math.pi / 2


def read_oxford_odometry(path: str | Path) -> PoseSequence:
    """Integrate an Oxford ``radar_odometry.csv`` into poses T_first_scan (x, y, yaw) per radar timestamp.

    Rows give T_dst_src in the Oxford frame (x forward, y right, yaw clockwise); they are converted to this
    project's frame (y left, yaw counter-clockwise). The first destination scan of the chain is the origin.

    Raises:
        PoseFileError: missing file, missing columns, non-numeric or non-finite values (naming the line), a row
            turning more than 90 degrees between two scans (yaw in degrees), or a chain with gaps.
    """
    path = Path(path)
    if not path.is_file():
        raise PoseFileError(f"{path}: no such odometry file")
    with path.open(newline="") as fh:
        reader = csv.reader(fh)
        header = [c.strip() for c in next(reader, [])]
        idx = {n: i for i, n in enumerate(header)}
        need = ("x", "y", "yaw", "source_radar_timestamp", "destination_radar_timestamp")
        missing = [n for n in need if n not in idx]
        if missing:
            raise PoseFileError(f"{path}:1: header lacks columns {missing} (expected {OXFORD_ODOMETRY_COLUMNS})")
        src, dst, rel = [], [], []
        for lineno, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            try:
                src.append(int(row[idx["source_radar_timestamp"]]))
                dst.append(int(row[idx["destination_radar_timestamp"]]))
                rel.append((float(row[idx["x"]]), -float(row[idx["y"]]), -float(row[idx["yaw"]])))
            except (ValueError, IndexError):
                raise PoseFileError(f"{path}:{lineno}: malformed odometry row {row}") from None
            if not all(math.isfinite(v) for v in rel[-1]):
                raise PoseFileError(f"{path}:{lineno}: NaN or infinite value")
            if abs(rel[-1][2]) > _MAX_FRAME_TURN_RAD:
                # one radar frame (0.25 s) never turns a vehicle by a right angle: a file in degrees reads its
                # every corner as several radians (a map 30-40 degrees off at its first corners, QA session 38)
                raise PoseFileError(f"{path}:{lineno}: yaw {-rel[-1][2]:g} turns more than "
                                    f"{math.degrees(_MAX_FRAME_TURN_RAD):.0f} degrees between two scans; the "
                                    "odometry's yaw is radians (degrees? convert the column with numpy.radians)")
    if not src:
        raise PoseFileError(f"{path}: no odometry rows")
    rel_arr = np.asarray(rel, dtype=np.float64)
    poses: dict[int, np.ndarray] = {dst[0]: np.zeros(3)}
    pending = list(range(len(src)))
    # Rows are normally a forward chain (row i's source = row i+1's destination); loop until no progress so
    # out-of-order rows still integrate, and report a broken chain instead of guessing.
    while pending:
        left = []
        for i in pending:
            if dst[i] in poses and src[i] not in poses:
                poses[src[i]] = compose(poses[dst[i]], rel_arr[i])
            elif src[i] in poses and dst[i] not in poses:
                poses[dst[i]] = compose(poses[src[i]], inverse(rel_arr[i]))
            elif src[i] not in poses and dst[i] not in poses:
                left.append(i)
        if len(left) == len(pending):
            raise PoseFileError(f"{path}: odometry chain is broken near radar timestamp {src[left[0]]}")
        pending = left
    t = np.asarray(sorted(poses), dtype=np.int64)
    p = np.stack([poses[int(k)] for k in t])
    return PoseSequence(t, p[:, :2], p[:, 2])


def write_oxford_odometry(poses: PoseSequence, path: str | Path) -> Path:
    """Write poses T_world_sensor as an Oxford ``radar_odometry.csv`` chain (row i: scan i+1 in scan i)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    p = poses.poses
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(OXFORD_ODOMETRY_COLUMNS)
        for i in range(len(poses) - 1):
            rel = compose(inverse(p[i]), p[i + 1])  # T_dst_src, dst = scan i, src = scan i+1
            t_src, t_dst = int(poses.timestamps_us[i + 1]), int(poses.timestamps_us[i])
            w.writerow([t_src, t_dst, repr(float(rel[0])), repr(float(-rel[1])), 0.0, 0.0, 0.0,
                        repr(float(-rel[2])), t_src, t_dst])
    return path


def _oxford_odometry_path(root: Path) -> Path:
    for cand in (root / "gt" / "radar_odometry.csv", root / "radar_odometry.csv"):
        if cand.is_file():
            return cand
    raise DatasetError(f"{root}: no Oxford odometry: expected gt/radar_odometry.csv")


def read_sequence_meta(root: str | Path) -> dict:
    """The simulator's ``reradar_sim.json`` in ``root`` as a dict ({} for real data without it)."""
    p = Path(root) / SIM_META_FILE
    if not p.is_file():
        return {}
    try:
        return json.loads(p.read_text())
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{p}: unreadable sequence metadata ({exc}); delete it or re-render") from exc


def write_sequence_meta(root: str | Path, meta: dict) -> Path:
    p = Path(root) / SIM_META_FILE
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(meta, indent=2, sort_keys=True))
    return p


def mid_sweep_poses_in(track: PoseSequence, stamps_us: np.ndarray, preset: RadarPreset) -> np.ndarray:
    """(N, 3) float64 poses (x m, y m, yaw rad) of scans with timestamps ``stamps_us`` (µs, first azimuth) at their
    mid-sweep times (``mid_sweep_times_us``), interpolated in ``track``; beyond its ends by up to the slack a scan
    may lie there (``POSE_SPAN_SLACK_US``) plus a sweep, its end steps continue (``PoseSequence.interpolate``)."""
    reach_us = POSE_SPAN_SLACK_US + int(round(preset.sweep_period_s * 1e6))
    return track.interpolate(mid_sweep_times_us(np.asarray(stamps_us, np.int64), preset), extrapolate_us=reach_us)


def pose_file_reader(track: PoseSequence, preset: RadarPreset) -> Callable[[np.ndarray], np.ndarray]:
    """The pose file ``track``'s pose at any scan time, as ``mid_sweep_poses_in`` reads it ((M,) int64 µs of first
    azimuths -> (M, 3) float64 x m, y m, yaw rad), and NaN rows where that reaches beyond the file (past its slack):
    what the map build's pose-clock check reads at shifted times (``maps.build.build_map(pose_at=...)``), so that a
    shift is judged on every pair the pose file covers, not only those inside the scans' own span (QA session 41: a
    pose file 18 s off, covering the scans and more, went unchecked on a 46 s stretch)."""
    reach_us = POSE_SPAN_SLACK_US + int(round(preset.sweep_period_s * 1e6))
    lo, hi = int(track.timestamps_us[0]) - reach_us, int(track.timestamps_us[-1]) + reach_us

    def read(stamps_us: np.ndarray) -> np.ndarray:
        mid = mid_sweep_times_us(np.asarray(stamps_us, np.int64), preset)
        out = track.interpolate(mid, extrapolate_us=reach_us)
        out[(mid < lo) | (mid > hi)] = np.nan
        return out

    return read


def layout_presets_ambiguous(layout: str) -> bool:
    """True when the radar presets of ``layout`` differ in range geometry (Boreas: boreas / boreas-2021), so a
    folder of that layout must name its preset."""
    from reradar_core.io.scan import same_range_geometry

    fits = [q for q in PRESETS.values() if q.dataset_layout == layout]
    return any(not same_range_geometry(q, fits[0]) for q in fits[1:])


def load_sequence(path: str | Path, layout: str | None = None,
                  preset: str | RadarPreset | None = None, pose_time_unit: str | None = None) -> Sequence:
    """Open a radar sequence folder in one of the real layouts (see the module docstring).

    Args:
        path: the sequence folder.
        layout: ``boreas``, ``oxford`` or ``mulran``; detected from the folder structure when None.
        preset: radar preset; when None, the simulator metadata's preset or the layout's own (Oxford, MulRan);
            a Boreas folder without simulator metadata must name it (boreas or boreas-2021: other bin sizes).
        pose_time_unit: unit of the Boreas / MulRan pose file's timestamps (``s``, ``ms``, ``us``, ``ns``);
            None: absolute UTC times or the format's unit, never a guess (``reradar_core.io.poses``).

    Returns:
        A ``Sequence`` whose ``poses`` hold one T_world_sensor per scan at its timestamp.

    Raises:
        DatasetError: missing folder, no scans, unknown layout, scans outside the pose time span, a scan whose
            file name and embedded first-azimuth time lie more than one sweep apart (``check_scan_name_times``).
        PoseFileError: malformed pose file.
    """
    root = Path(path)
    if not root.is_dir():
        raise DatasetError(f"{root}: is a file; give the sequence folder (the one holding radar/ or sensor_data/)"
                           if root.is_file() else f"{root}: sequence folder does not exist")
    layout = detect_layout(root) if layout is None else layout.lower()
    if layout not in LAYOUTS:
        raise DatasetError(f"unknown dataset layout {layout!r}; choose one of {LAYOUTS}")
    meta = read_sequence_meta(root)
    if preset is None and "preset" not in meta and layout_presets_ambiguous(layout):
        # a real Boreas folder: the 3,360-bin scans fit boreas and boreas-2021, whose bins differ by 36 %; the layout's
        # default read every range of a 2021 recording 1.36x too long and answered 1.5 m off at confidence 1 (QA)
        fits = [q for q in PRESETS.values() if q.dataset_layout == layout]
        raise DatasetError(
            f"{root}: a {layout}-layout folder does not say which radar recorded it, and its presets differ in "
            f"range geometry ({preset_bin_sizes(fits)}): pass the "
            "one it was recorded with (--preset; Boreas: boreas before the sensor upgrade, boreas-2021 after)")
    recorded = get_preset(meta.get("preset", _DEFAULT_PRESET[layout]))
    p = get_preset(preset) if preset is not None else recorded
    if preset is not None and (p.range_resolution_m, p.range_offset_m) != (recorded.range_resolution_m,
                                                                           recorded.range_offset_m):
        if "preset" in meta:  # the simulator recorded the sensor: another preset would misread every range
            raise DatasetError(f"{root}: rendered with radar preset {recorded.name!r} ({SIM_META_FILE}), not "
                               f"{p.name!r}: {range_grid_difference(recorded, p)}; drop the preset or pass the "
                               "recorded one")
        if p.dataset_layout != layout:  # a Boreas folder naming boreas-2021 is no surprise (it must name one)
            logger.warning("%s: a %s-layout folder read with radar preset %r (%s m/bin, a %s-layout radar): right "
                           "for such scans given map-frame poses in this layout, else check the preset", root,
                           layout, p.name, p.range_resolution_m, p.dataset_layout)
    paths, stamps = _list_scans(root, layout)
    check_scan_name_times(paths, stamps, p, layout)
    if layout == "boreas":
        pose_file = root / "applanix" / "radar_poses.csv"
        if not pose_file.is_file():
            raise DatasetError(f"{root}: missing applanix/radar_poses.csv")
        # our simulator writes GPSTime in µs, also for trajectories whose time starts at 0 (no magnitude rule
        # can tell those apart); real files must hold absolute times or the reader refuses to guess
        track = read_boreas_radar_poses(pose_file, pose_time_unit or ("us" if meta else None)).sorted()
    elif layout == "mulran":
        pose_file = root / "global_pose.csv"
        if not pose_file.is_file():
            raise DatasetError(f"{root}: missing global_pose.csv")
        # ns by the format; our simulator's folders hold relative ns (e.g. from 1,000 s = 1e12 ns, which reads as an
        # absolute time in ms: QA session 24), so a render is read in ns, as the Boreas branch reads it in µs
        track = read_mulran_global_pose(pose_file, pose_time_unit or ("ns" if meta else None)).sorted()
    else:
        pose_file = _oxford_odometry_path(root)
        track = read_oxford_odometry(pose_file)
        if "oxford_T_world_origin" in meta:
            # Simulated Oxford-layout sequences record the world pose of the odometry origin so that
            # several traversals share one map frame; real Oxford data starts at the identity.
            origin = np.asarray(meta["oxford_T_world_origin"], dtype=np.float64)
            world = compose(origin[None, :], track.poses)
            track = PoseSequence(track.timestamps_us, world[:, :2], world[:, 2])
        check_pose_speed(track, str(pose_file), how="Oxford odometry timestamps are microseconds")
    if layout == "oxford":
        known = np.isin(stamps, track.timestamps_us)
        if not np.all(known):
            bad = paths[int(np.argmin(known))]
            raise DatasetError(f"{bad}: scan timestamp not in the odometry file {pose_file}")
        lookup = np.searchsorted(track.timestamps_us, stamps)
        poses = track.subset(lookup)
    else:
        unit_used = pose_time_unit or ("us" if layout == "boreas" and meta else "ns" if layout == "mulran" else None)
        check_pose_time_unit(track, stamps, unit_used, str(pose_file))
        check_pose_speed(track, str(pose_file))
        check_pose_span(track, stamps, [str(p) for p in paths], str(pose_file))
        interp = track.interpolate(stamps, extrapolate_us=POSE_SPAN_SLACK_US)  # scans within the span's slack
        poses = PoseSequence(stamps, interp[:, :2], interp[:, 2])
    return Sequence(root.name, p, layout, paths, stamps, poses, root, track.sorted())


def range_grid_difference(recorded: RadarPreset, read_as: RadarPreset, at_m: float = 100.0) -> str:
    """How far off ranges are when scans recorded with ``recorded`` are read with ``read_as``'s range grid, in
    words: the bin-size difference in percent (one decimal) and where a return at ``at_m`` metres would land."""
    bins = (at_m - recorded.range_offset_m) / recorded.range_resolution_m
    read_m = read_as.range_offset_m + bins * read_as.range_resolution_m
    pct = 100.0 * (read_as.range_resolution_m / recorded.range_resolution_m - 1.0)
    return (f"its range bins would be {pct:+.1f} % off ({recorded.range_resolution_m:g} vs "
            f"{read_as.range_resolution_m:g} m/bin, offsets {recorded.range_offset_m:g} vs "
            f"{read_as.range_offset_m:g} m): a return at {at_m:g} m would be read at {read_m:.2f} m")


#: a pose file whose time span is this many times the scans' (or more), with the scans crowded onto a sliver of its
#: path, was read in a unit 1000x too coarse (a 1e3 unit error gives 1e3 or more; a folder of a real drive's scans
#: covers the pose file's span up to the drive's start and end)
POSE_UNIT_SPAN_RATIO = 500.0
#: ... and the pose file's path is longer than this, metres (a drive, not a vehicle standing still; 50 m until
#: session 24, which let a 47.5 m clip read in ms instead of µs place every scan on its first pose: QA)
POSE_UNIT_MIN_PATH_M = 5.0
#: ... and the scans' interpolated path is shorter than this fraction of it
POSE_UNIT_PATH_FRACTION = 0.01


def likely_time_unit(raw_span: float, expected_span_us: float) -> str:
    """The unit (of ``TIME_UNITS``) in which ``raw_span`` file units last closest to ``expected_span_us``
    (log scale): what a pose file's times most likely are."""
    from reradar_core.io.poses import TIME_UNITS

    return min(TIME_UNITS, key=lambda u: abs(np.log(max(raw_span * TIME_UNITS[u], 1e-9) / expected_span_us)))


def check_pose_time_unit(track: PoseSequence, stamps_us: np.ndarray, unit: str | None,
                         pose_file: str = "the pose file", how: str = "pass --time-unit {unit}") -> None:
    """Refuse a pose file whose times were converted with a unit 1000x (or more) off, before any pose is
    interpolated: the scans' times (µs, from their file names) are the reference.

    Two signs, each of which a 1e3 unit error always shows and a folder of a real drive does not:

    - the unit is too fine: the pose file's time span is ``POSE_UNIT_SPAN_RATIO`` x shorter than the scans'
      (the scans would lie outside it);
    - the unit is too coarse: the pose file's span is ``POSE_UNIT_SPAN_RATIO`` x the scans' or more, its path is
      longer than ``POSE_UNIT_MIN_PATH_M`` while the scans would interpolate onto less than
      ``POSE_UNIT_PATH_FRACTION`` of it, and fewer poses than half the scans fall within the scans' time
      window (every scan would be placed on the drive's first metres; a crop of a real drive keeps the poses
      of its scans).

    Args:
        track: the pose file's poses, sorted, times in µs after the conversion. stamps_us: (N,) int64 scan
            times, µs. unit: the unit the pose times were read in (None: from the file). pose_file: for the
            message. how: how to set the likely unit, ``{unit}`` standing for it (the command line's option by
            default; the service says how to name the column).

    Raises:
        DatasetError: naming the likely unit and the option that sets it.
    """
    from reradar_core.io.poses import TIME_UNITS

    t = np.sort(np.asarray(stamps_us, np.int64))
    if len(t) < 2 or len(track) < 2:
        return
    scans_span = float(t[-1] - t[0])
    pose_span = float(track.timestamps_us[-1] - track.timestamps_us[0])
    if scans_span <= 0 or pose_span <= 0:
        return
    read_as = unit or "the unit the file implies"
    raw_span = pose_span / TIME_UNITS.get(str(unit), 1.0) if unit else pose_span
    likely = likely_time_unit(raw_span, scans_span) if unit else None
    advice = (f"the pose times are probably {likely}: {how.format(unit=likely)}" if likely and likely != unit
              else f"check the pose file's time unit ({how.format(unit='s|ms|us|ns')})")
    if pose_span * POSE_UNIT_SPAN_RATIO <= scans_span:
        raise DatasetError(f"{pose_file}: its times read as {read_as} span {pose_span / 1e6:.6g} s, but the scans' "
                           f"times (from their file names, µs) span {scans_span / 1e6:.6g} s; {advice}")
    if pose_span < POSE_UNIT_SPAN_RATIO * scans_span:
        return
    pose_path = track.path_length_m()
    if pose_path <= POSE_UNIT_MIN_PATH_M:
        return
    at = track.interpolate(t)
    scans_path = float(np.sum(np.linalg.norm(np.diff(at[:, :2], axis=0), axis=1)))
    inside = int(np.count_nonzero((track.timestamps_us >= t[0]) & (track.timestamps_us <= t[-1])))
    if scans_path < POSE_UNIT_PATH_FRACTION * pose_path and inside < len(t) / 2:
        raise DatasetError(
            f"{pose_file}: its times read as {read_as} span {pose_span / 1e6:.6g} s and {pose_path:.0f} m of path, "
            f"but the {len(t)} scans' times (from their file names, µs) span {scans_span / 1e6:.6g} s: every scan "
            f"would be placed on {scans_path:.1f} m of the drive; {advice}")


#: the fastest mean speed (m/s) of a drive a pose file may describe: beyond it its positions are not metres (a file
#: in millimetres drives 1000x too fast, one in centimetres 100x) or its times are read in a unit too fine
#: (``check_pose_speed``). The speed of sound: far above any road vehicle's (~100 m/s), so a pose file of sparse
#: or jumpy samples is never refused, and below a millimetre file of any drive faster than walking pace.
MAX_PLAUSIBLE_SPEED_M_S = 340.0
#: ... judged on pose files with at least this much path, metres
PLAUSIBLE_SPEED_MIN_PATH_M = 20.0


def check_pose_speed(track: PoseSequence, pose_file: str = "the pose file",
                     how: str = "--time-unit") -> None:
    """Refuse a pose file whose drive is faster than any road vehicle (mean speed above
    ``MAX_PLAUSIBLE_SPEED_M_S`` over at least ``PLAUSIBLE_SPEED_MIN_PATH_M`` of path): its positions are in another
    unit than metres, or its times in a finer one than they are read in. A map built from it would hold
    keyframes 1000x apart, and a benchmark would find no revisit at all, without a word (QA session 36). Also refused:
    a single step of more than ``PLAUSIBLE_SPEED_MIN_PATH_M`` between two poses, faster than that (a position
    glitch of one row; QA session 38).

    Args:
        track: the pose file's poses, sorted, µs and metres. pose_file: for the message. how: how the time unit
            is set (the command line's option by default; the service says how to name the column), as
            ``check_pose_time_unit``'s.

    Raises:
        DatasetError: the speed, and what to check.
    """
    if len(track) < 2:
        return
    span_s = (int(track.timestamps_us[-1]) - int(track.timestamps_us[0])) / 1e6
    path_m = track.path_length_m()
    if span_s > 0 and path_m >= PLAUSIBLE_SPEED_MIN_PATH_M and path_m / span_s > MAX_PLAUSIBLE_SPEED_M_S:
        raise DatasetError(f"{pose_file}: its poses drive {path_m:.4g} m in {span_s:.4g} s, a mean speed of "
                           f"{path_m / span_s:.3g} m/s (faster than sound; a road vehicle drives up to ~100 m/s): "
                           "positions must be metres (a file in millimetres or centimetres?), and the times in the "
                           f"unit they are read in ({how})")
    check_pose_steps(track, pose_file)


def check_pose_steps(track: PoseSequence, pose_file: str = "the pose file") -> None:
    """Refuse a single step between two poses of more than ``PLAUSIBLE_SPEED_MIN_PATH_M``, faster than
    ``MAX_PLAUSIBLE_SPEED_M_S``: one row off by hundreds of metres (a GNSS glitch) passes the mean speed, and moved
    the keyframes around it there (QA session 38).

    Raises:
        DatasetError: naming the row's time, the step and how many such steps there are.
    """
    if len(track) < 2:
        return
    step = np.linalg.norm(np.diff(track.xy, axis=0), axis=1)
    dt_s = np.diff(track.timestamps_us).astype(np.float64) / 1e6
    with np.errstate(divide="ignore", invalid="ignore"):
        jump = (step > PLAUSIBLE_SPEED_MIN_PATH_M) & (step > MAX_PLAUSIBLE_SPEED_M_S * dt_s)
    if np.any(jump):
        i = int(np.argmax(jump))
        raise DatasetError(f"{pose_file}: the pose at {int(track.timestamps_us[i + 1])} us lies {step[i]:.4g} m from "
                           f"the one {dt_s[i]:.4g} s before it ({step[i] / max(dt_s[i], 1e-9):.3g} m/s, faster than "
                           f"sound; {int(jump.sum())} such step(s)): a position glitch? fix or remove that row")


#: how far beyond the first / last pose a scan may lie (pose files sample the trajectory at their own rate), µs
POSE_SPAN_SLACK_US = 500_000
#: the longest gap between two pose rows a scan's pose may be interpolated across, µs: twice the 1 s of a 1 Hz GNSS
#: log; across a longer gap (an outage) the drive between the rows is unknown (QA session 40: a 10 s gap around a
#: corner put keyframes up to 16 m and 44 degrees off, answered `localized` at confidence 1)
POSE_GAP_MAX_US = 2_000_000


def check_pose_span(track: PoseSequence, stamps_us: np.ndarray, names: list[str], pose_file: str = "the pose file",
                    outside_hint: str = "") -> None:
    """Refuse scans whose times lie outside ``track``'s time span (plus ``POSE_SPAN_SLACK_US`` at each end), or
    inside a gap of more than ``POSE_GAP_MAX_US`` between two pose rows: their poses would be extrapolated or
    bridged by a straight line, i.e. guessed.

    Args:
        track: the pose file's poses, sorted. stamps_us: (N,) int64 scan times, µs. names: the N scans' names,
            for the message. pose_file: the pose file's name, for the message. outside_hint: appended to the
            message of a scan outside the span (e.g. how the caller's scans are named).

    Raises:
        DatasetError: naming the first scan outside and the pose file.
    """
    t = np.asarray(stamps_us, np.int64)
    # Python ints: a timestamp near 2^62 minus the slack must not wrap around
    lo, hi = int(track.timestamps_us[0]) - POSE_SPAN_SLACK_US, int(track.timestamps_us[-1]) + POSE_SPAN_SLACK_US
    outside = [not lo <= int(v) <= hi for v in t]
    if any(outside):
        i = outside.index(True)
        first, last = int(track.timestamps_us[0]), int(track.timestamps_us[-1])
        start_off, end_off = int(np.min(t)) - first, int(np.max(t)) - last
        clock = ""
        if abs(start_off - end_off) <= 1_000_000 and abs(start_off + end_off) / 2 >= POSE_SPAN_SLACK_US:
            # both ends shifted alike: one recording, two clocks (the pose-clock check cannot run on it)
            shift_s = (start_off + end_off) / 2e6
            clock = (f"; both ends of the scans' span lie {shift_s:+.2f} s from the pose file's: a pose file on another "
                     f"clock{gps_offset_hint(shift_s)}? Add "
                     f"{shift_s:+.2f} s to its times")
        elif last - first >= int(np.max(t)) - int(np.min(t)) and (start_off < 0) != (end_off > 0):
            # long enough to cover the scans but off at one end only: a wider log on another clock, or another
            # drive's (QA session 41: a hint only for equal spans rarely showed, real logs run beyond the scans)
            clock = ("; the pose file is long enough to cover the scans but starts "
                     f"{abs(start_off) / 1e6:.2f} s {'after' if start_off < 0 else 'before'} them and ends "
                     f"{abs(end_off) / 1e6:.2f} s {'before' if end_off > 0 else 'after'} them: a pose file on another "
                     "clock (GPS time runs 18 s ahead of UTC) or of another drive?")
        raise DatasetError(f"{names[i]}: scan time {int(t[i])} us lies outside the pose file's time span, {first} to "
                           f"{last} us ({pose_file}; the scans span {int(np.min(t))} to {int(np.max(t))} us"
                           f"{': relative pose times against absolute scan names?' if last < 1e14 <= int(t[i]) else ''})"
                           f"{clock}{outside_hint}")
    stamps = np.asarray(track.timestamps_us, np.int64)
    after = np.clip(np.searchsorted(stamps, t, side="left"), 1, len(stamps) - 1) if len(stamps) > 1 else None
    if after is not None:
        exact = stamps[after] == t
        exact |= stamps[after - 1] == t
        gap = stamps[after] - stamps[after - 1]
        inside = (t > stamps[0]) & (t < stamps[-1])
        bridged = inside & ~exact & (gap > POSE_GAP_MAX_US)
        if bridged.any():
            i = int(np.flatnonzero(bridged)[0])
            raise DatasetError(
                f"{names[i]}: scan time {int(t[i])} us falls in a {gap[i] / 1e6:.3g} s gap between two poses "
                f"({int(stamps[after[i] - 1])} and {int(stamps[after[i]])} us, {pose_file}; {int(bridged.sum())} "
                f"scan(s) in such gaps): its pose would be a straight line across the gap; give poses at most "
                f"{POSE_GAP_MAX_US / 1e6:g} s apart there, or leave those scans out")


def write_sequence_scan(root: str | Path, layout: str, scan: RadarScan) -> Path:
    """Write ``scan`` into sequence ``root`` in ``layout``, named by its first-azimuth timestamp."""
    return write_navtech_png(scan, scan_path(root, layout, scan.timestamp_us))


def write_sequence_poses(root: str | Path, layout: str, poses: PoseSequence) -> Path:
    """Write ``poses`` (T_world_sensor at their timestamps: every scan's, and any others, e.g. the drive's between
    scans) in ``layout``'s pose file; ``load_sequence`` looks each scan's pose up by its timestamp and keeps the
    whole track for interpolation."""
    root = Path(root)
    if layout == "boreas":
        return write_boreas_radar_poses(poses, root / "applanix" / "radar_poses.csv")
    if layout == "mulran":
        return write_mulran_global_pose(poses, root / "global_pose.csv")
    if layout == "oxford":
        return write_oxford_odometry(poses, root / "gt" / "radar_odometry.csv")
    raise DatasetError(f"unknown dataset layout {layout!r}; choose one of {LAYOUTS}")
