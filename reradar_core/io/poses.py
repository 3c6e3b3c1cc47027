"""Pose files: Boreas ``applanix/radar_poses.csv``, MulRan ``global_pose.csv`` and a plain ``t,x,y,yaw`` CSV.

All readers return a ``PoseSequence`` of planar poses T_world_sensor in metres / radians with int64
microsecond timestamps. Malformed files raise ``PoseFileError`` naming the file and the 1-based line.

Time units are never guessed from relative values. Each reader takes ``time_unit`` (``s``, ``ms``, ``us``,
``ns``); without it:

- a unit is taken only when every timestamp is an absolute UTC time between the years 2000 and 2100 in exactly
  one unit (the four windows do not overlap: seconds ~1e9, ms ~1e12, µs ~1e15, ns ~1e18), as in the published
  Boreas files (2021-08-05 stores GPSTime in ns, 2021-09-02 in µs);
- MulRan ``global_pose.csv`` is in nanoseconds by its format definition; values that are absolute times in
  another unit are refused;
- Boreas ``radar_poses.csv`` and ``t,x,y,yaw`` CSVs with relative times (e.g. starting at 0) are refused with a
  message asking for the unit. A ``t,x,y,yaw`` CSV can carry the unit in its header (``t_s``, ``t_ms``,
  ``t_us``, ``t_ns``); ``write_txyyaw_csv`` writes ``t_s``.

The yaw of a ``t,x,y,yaw`` CSV is in radians unless its header names the column ``yaw_deg`` (degrees) or
``yaw_rad`` (radians, stated). A plain ``yaw`` column (or a file without a header) with any ``|yaw| > 2 pi`` is
refused: those are almost surely degrees, and reading them as radians would turn every keyframe the wrong way.
Positions beyond ``MAX_ABS_COORDINATE_M`` from the origin are refused in every format.
"""

from __future__ import annotations

import csv
import math
from array import array
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from reradar_core.bounds import MAX_ABS_COORDINATE_M
from reradar_core.errors import PoseFileError, TimeUnitError, shorten_echo
from reradar_core.geometry.se2 import wrap_angle

__all__ = [
    "PoseSequence",
    "read_boreas_radar_poses",
    "write_boreas_radar_poses",
    "read_mulran_global_pose",
    "write_mulran_global_pose",
    "read_txyyaw_csv",
    "write_txyyaw_csv",
    "read_poses",
    "gps_time_to_us",
    "gps_offset_hint",
    "TIME_UNITS",
    "absolute_time_unit",
    "to_microseconds",
    "MAX_ABS_COORDINATE_M",
    "TXYYAW_YAW_HEADERS",
    "travel_yaw_mismatch_deg",
]

#: Timestamp units a pose file may use: name -> microseconds per unit.
TIME_UNITS: dict[str, float] = {"s": 1e6, "ms": 1e3, "us": 1.0, "ns": 1e-3}
#: Absolute UTC times accepted without an explicit unit: 2000-01-01 .. 2100-01-01, in seconds.
_EPOCH_WINDOW_S = (946_684_800.0, 4_102_444_800.0)
_UNIT_SCALE_FROM_S = {"s": 1.0, "ms": 1e3, "us": 1e6, "ns": 1e9}
#: read in a declared unit, times up to this (seconds) can be a recording's relative clock (a year)
_MAX_RELATIVE_TIME_S = 366 * 86_400.0
#: Header names of the time column of a t,x,y,yaw CSV and the unit each declares (None: not declared).
TXYYAW_TIME_HEADERS: dict[str, str | None] = {"t": None, "t_s": "s", "t_ms": "ms", "t_us": "us", "t_ns": "ns"}
#: Header names of the yaw column of a t,x,y,yaw CSV and the unit each declares (``yaw``: radians, checked to
#: be within +-2 pi; ``yaw_rad``: radians, any value).
TXYYAW_YAW_HEADERS: dict[str, str] = {"yaw": "rad", "yaw_rad": "rad", "yaw_deg": "deg"}
#: A plain ``yaw`` column holding a value beyond 2 pi (+ rounding slack) is taken to be in degrees and refused.
_MAX_PLAIN_YAW_RAD = 2.0 * np.pi + 1e-6

BOREAS_COLUMNS = (
    "GPSTime,easting,northing,altitude,vel_east,vel_north,vel_up,roll,pitch,heading,angvel_z,angvel_y,angvel_x"
).split(",")


@dataclass
class PoseSequence:
    """Planar poses T_world_sensor along a trajectory.

    Attributes:
        timestamps_us: (N,) int64 UTC microseconds, strictly increasing after ``sorted()`` (the readers refuse
            a file that holds one time twice).
        xy: (N, 2) float64 metres in the world (map) frame, x east / y north for GNSS data.
        yaw: (N,) float64 radians, counter-clockwise from world +x, wrapped to (-pi, pi].
    """

    timestamps_us: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray

    def __post_init__(self) -> None:
        t = np.asarray(self.timestamps_us)
        if t.dtype.kind == "f" and t.size and not (np.isfinite(t).all() and np.all(t == np.round(t))):
            # int64 would truncate seconds (1.25 -> 1) into repeated, wrong times without a word
            raise PoseFileError("pose timestamps must be whole microseconds; got fractional values (seconds or "
                                "milliseconds? multiply to microseconds)")
        self.timestamps_us = t.astype(np.int64).reshape(-1)
        xy = np.asarray(self.xy, dtype=np.float64)
        if xy.shape == (2,):
            xy = xy.reshape(1, 2)
        if xy.ndim != 2 or xy.shape[1] != 2:  # a (2, N) array would be interleaved into other positions
            raise PoseFileError(f"pose positions must be (N, 2) x, y in metres, got shape {xy.shape}")
        self.xy = xy
        self.yaw = wrap_angle(np.asarray(self.yaw, dtype=np.float64).reshape(-1))
        n = len(self.timestamps_us)
        if self.xy.shape[0] != n or self.yaw.shape[0] != n:
            raise PoseFileError(f"pose arrays disagree in length: {n}, {self.xy.shape[0]}, {self.yaw.shape[0]}")
        self._in_order = bool(np.all(np.diff(self.timestamps_us) >= 0))

    def __len__(self) -> int:
        return int(self.timestamps_us.shape[0])

    @property
    def poses(self) -> np.ndarray:
        """(N, 3) float64 array of (x, y, yaw)."""
        return np.column_stack([self.xy, self.yaw])

    def sorted(self) -> PoseSequence:
        order = np.argsort(self.timestamps_us, kind="stable")
        return PoseSequence(self.timestamps_us[order], self.xy[order], self.yaw[order])

    def subset(self, index: np.ndarray | slice) -> PoseSequence:
        return PoseSequence(self.timestamps_us[index], self.xy[index], self.yaw[index])

    def interpolate(self, t_us: np.ndarray | int, extrapolate_us: int = 0) -> np.ndarray:
        """Poses at times ``t_us`` by linear interpolation (yaw on the circle), clamped at the ends.

        Args:
            extrapolate_us: times up to this far beyond the first / last pose continue the first / last step's
                motion (linear, yaw too) instead of holding the end pose; farther ones are clamped. 0 (default):
                clamped. A scan's mid-sweep time lies half a sweep after its timestamp, so a pose file ending at the
                last scan held its pose ~1 m back at driving speed (QA, session 24).

        Returns:
            (..., 3) float64 (x, y, yaw) with the shape of ``t_us`` plus a trailing 3.
        """
        if not self._in_order:  # np.interp reads unsorted times as garbage
            raise PoseFileError("pose timestamps are not in time order; interpolate the sorted() sequence")
        t = np.asarray(t_us, dtype=np.float64)
        ts = self.timestamps_us.astype(np.float64)
        x = np.interp(t, ts, self.xy[:, 0])
        y = np.interp(t, ts, self.xy[:, 1])
        yaw_unwrapped = np.unwrap(self.yaw)
        yaw_u = np.interp(t, ts, yaw_unwrapped)
        if extrapolate_us > 0 and len(ts) >= 2:
            for end, nxt, beyond in ((-1, -2, (t > ts[-1]) & (t <= ts[-1] + extrapolate_us)),
                                     (0, 1, (t < ts[0]) & (t >= ts[0] - extrapolate_us))):
                if not beyond.any():
                    continue
                dt = ts[end] - ts[nxt]
                frac = (t[beyond] - ts[end]) / dt  # in steps of the end segment (dt of either sign)
                x[beyond] = self.xy[end, 0] + frac * (self.xy[end, 0] - self.xy[nxt, 0])
                y[beyond] = self.xy[end, 1] + frac * (self.xy[end, 1] - self.xy[nxt, 1])
                yaw_u[beyond] = yaw_unwrapped[end] + frac * (yaw_unwrapped[end] - yaw_unwrapped[nxt])
        return np.stack([x, y, wrap_angle(yaw_u)], axis=-1)

    def path_length_m(self) -> float:
        return float(np.sum(np.linalg.norm(np.diff(self.xy, axis=0), axis=1)))


def gps_offset_hint(offset_s: float) -> str:
    """" (GPS time runs 18 s ahead of UTC)" for a clock offset of 17-19 s (either way), else "": what a message about
    a pose file on another clock than its scans' adds when the offset looks like GPS time against UTC."""
    return " (GPS time runs 18 s ahead of UTC)" if 17 <= abs(offset_s) <= 19 else ""


def _check_unit(unit: str) -> str:
    u = unit.strip().lower().replace("µs", "us")
    if u not in TIME_UNITS:
        raise PoseFileError(f"unknown time unit {unit!r}; choose one of {sorted(TIME_UNITS)}")
    return u


def absolute_time_unit(values: np.ndarray) -> str | None:
    """The unit in which every value is an absolute UTC time between 2000 and 2100, or None.

    The windows of the four units (s, ms, µs, ns) are disjoint, so at most one fits. Relative times (a
    trajectory starting at 0) fit none: their unit cannot be told from the numbers.
    """
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size == 0 or not np.all(np.isfinite(v)):
        return None
    lo, hi = float(v.min()), float(v.max())
    for unit, scale in _UNIT_SCALE_FROM_S.items():
        if _EPOCH_WINDOW_S[0] * scale <= lo and hi <= _EPOCH_WINDOW_S[1] * scale:
            return unit
    return None


def to_microseconds(values: np.ndarray | list, unit: str) -> np.ndarray:
    """Timestamps in ``unit`` -> int64 microseconds.

    Integer inputs convert exactly (ns values of ~1.6e18 do not fit a float64 mantissa): ns are truncated
    to whole µs, s / ms multiplied. Float inputs are rounded to the nearest µs.

    Raises:
        PoseFileError: unknown unit, or values that overflow int64 µs in that unit (a wrong unit).
    """
    u = _check_unit(unit)
    v = np.asarray(values)
    peak = float(np.max(np.abs(v.astype(np.float64)))) if v.size else 0.0
    if peak * TIME_UNITS[u] >= 2.0**63:  # int64 would wrap around silently
        raise PoseFileError(f"timestamps up to {peak:.6g} {u} overflow int64 microseconds; is the time unit "
                            f"{u!r} right?")
    if np.issubdtype(v.dtype, np.integer):
        v = v.astype(np.int64)
        if u == "ns":
            return v // 1000
        return v * int(TIME_UNITS[u])
    return np.round(v.astype(np.float64) * TIME_UNITS[u]).astype(np.int64)


def gps_time_to_us(values: np.ndarray, unit: str | None = None, source: str = "timestamps") -> np.ndarray:
    """Convert Boreas GPSTime values (or any pose timestamps) to int64 microseconds.

    Args:
        values: (N,) timestamps, int64 (exact) or float64.
        unit: ``s``, ``ms``, ``us`` or ``ns``; None = only absolute UTC times, whose unit follows from their
            magnitude (``absolute_time_unit``).
        source: what the values are, for the error message (e.g. ``path:GPSTime``).

    Raises:
        PoseFileError: no unit given and the values are not absolute UTC times in exactly one unit.
    """
    if unit is None:
        unit = absolute_time_unit(values)
        if unit is None:
            v = np.asarray(values, dtype=np.float64)
            span = f"{v.min():.6g} .. {v.max():.6g}" if v.size else "none"
            problem = (f"timestamps {span} are not absolute UTC times (2000-2100) in s, ms, us or ns, so their unit "
                       "is ambiguous")
            raise TimeUnitError(
                f"{source}: {problem}; give it explicitly: --time-unit s|ms|us|ns on the command line "
                "(time_unit= in Python), or a t_s / t_ms / t_us / t_ns column header in a t,x,y,yaw CSV", problem)
    else:
        absolute = absolute_time_unit(values)
        v = np.abs(np.asarray(values, dtype=np.float64))
        in_unit_s = float(v.max()) / _UNIT_SCALE_FROM_S[_check_unit(unit)] if v.size else 0.0
        # e.g. Boreas ns read as us (a time 50,000 years on) is refused; values that fit an absolute time in another
        # unit but read in the declared one are a drive's relative clock (a render starting at 1,000 s = 1e9 us,
        # which also reads as absolute s in 2001) are what the user said (QA, session 24: the advice went in a circle)
        if absolute is not None and absolute != _check_unit(unit) and in_unit_s > _MAX_RELATIVE_TIME_S:
            raise PoseFileError(f"{source}: the timestamps are absolute UTC times in {absolute}, not {unit}; "
                                f"give --time-unit {absolute} (or none: absolute times need none)")
    return to_microseconds(values, unit)


def _refuse_repeated_times(t_us: np.ndarray, path: Path) -> None:
    """Two poses at one time (after the conversion to µs) are two answers for one instant: refused, never one of
    them picked (interpolation would keep either without a word)."""
    t = np.sort(np.asarray(t_us, np.int64))
    same = np.flatnonzero(np.diff(t) == 0)
    if same.size:
        raise PoseFileError(f"{path}: {same.size} timestamp(s) appear twice (first: {int(t[same[0]])} µs); each "
                            "pose needs its own time")


def _missing_pose_file(path: Path) -> str:
    """Why ``path`` (not a file) cannot be read as a pose file, in words."""
    if path.is_dir():
        return f"{path}: is a folder, not a pose file (give the CSV itself, e.g. applanix/radar_poses.csv)"
    return f"{path}: no such pose file"


@dataclass(frozen=True)
class _PoseTable:
    """The columns a reader needs, parsed while the file is read (one row's strings at a time: a 24 MB Boreas
    file's rows kept as lists of strings took +320 MB, QA session 40; these arrays take ~40 bytes a row).

    Attributes:
        header: the header line's cells (stripped), or None.
        linenos: (N,) int64, each row's 1-based line number (for messages).
        times: (N,) the time column exactly: int64 when every value is an integer (ns stamps need all 64 bits),
            else float64. No unit applied.
        values: (N, K) float64, the value columns in the order asked for.
    """

    header: list[str] | None
    linenos: np.ndarray
    times: np.ndarray
    values: np.ndarray


def _read_table(path: Path, min_cols: int, header_first: str | None, expected: str,
                columns: Callable[[list[str] | None], tuple[int, list[int]]]) -> _PoseTable:
    """Read a pose CSV row by row into ``_PoseTable``: blank lines skipped, an optional header line (first cell
    ``header_first``, any case), every other row needs ``min_cols`` cells. ``columns(header)`` names the time
    column and the value columns (it may raise ``PoseFileError`` for a header that lacks one). The first bad row
    (too few cells, a non-numeric or non-finite value) is refused naming its line."""
    if not path.is_file():
        raise PoseFileError(_missing_pose_file(path))
    header: list[str] | None = None
    time_col: int | None = None
    value_cols: list[int] = []
    linenos = array("q")
    int_times: array | None = array("q")  # until a time is not an integer; then float_times holds every time
    float_times = array("d")
    values = array("d")
    with path.open(newline="", encoding="utf-8-sig") as fh:  # a UTF-8 BOM (spreadsheet exports) is no data
        for lineno, row in enumerate(_csv_rows(path, fh), start=1):
            if not row or all(not c.strip() for c in row):
                continue
            if lineno == 1 and header_first is not None and row[0].strip().lower() == header_first.lower():
                header = [c.strip() for c in row]
                continue
            if time_col is None:
                time_col, value_cols = columns(header)
                min_cols = max(min_cols, time_col + 1, *(c + 1 for c in value_cols))
            if len(row) < min_cols:
                raise PoseFileError(f"{path}:{lineno}: expected at least {min_cols} columns"
                                    f"{f' ({expected})' if expected else ''}, got {len(row)}")
            text = row[time_col].strip()
            if int_times is not None:
                try:
                    int_times.append(int(text))
                except ValueError:
                    float_times = array("d", (float(v) for v in int_times))
                    int_times = None
                except OverflowError:  # beyond int64 (year 2262 in ns): a corrupt row; read as a float it took
                    # every other ns time with it onto the float grid, 1 us off (QA session 41)
                    when = "before the year 1678" if text.startswith("-") else "after the year 2262"
                    raise PoseFileError(f"{path}:{lineno}: timestamp {shorten_echo(text)} is beyond a 64-bit integer "
                                        f"({when} even in nanoseconds): a corrupt row?") from None
            if int_times is None:
                try:
                    t = float(text)
                except ValueError:
                    raise PoseFileError(f"{path}:{lineno}: timestamp {text!r} is not a number") from None
                if not math.isfinite(t):
                    raise PoseFileError(f"{path}:{lineno}: timestamp {text!r} is not finite")
                float_times.append(t)
            try:
                vals = [float(row[c]) for c in value_cols]
            except (ValueError, IndexError):
                raise PoseFileError(f"{path}:{lineno}: non-numeric value in {row[:max(value_cols) + 1]}") from None
            if not all(math.isfinite(v) for v in vals):
                raise PoseFileError(f"{path}:{lineno}: NaN or infinite value")
            values.extend(vals)
            linenos.append(lineno)
    if not linenos:
        raise PoseFileError(f"{path}: no pose rows")
    times = (np.frombuffer(int_times, dtype=np.int64) if int_times is not None
             else np.frombuffer(float_times, dtype=np.float64))
    return _PoseTable(header, np.frombuffer(linenos, dtype=np.int64),
                      times.copy(), np.frombuffer(values, dtype=np.float64).reshape(len(linenos), len(value_cols)).copy())


def _csv_rows(path: Path, fh: TextIO) -> Iterator[list[str]]:
    """``csv.reader`` rows of ``fh``; a field beyond the csv module's limit (128 KiB: no pose file has one) is a
    ``PoseFileError`` naming its line (QA session 41: a 50 MB line was a 500 through POST /maps)."""
    reader = csv.reader(fh)
    while True:
        try:
            row = next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            raise PoseFileError(f"{path}:{reader.line_num}: not a pose file row ({exc})") from None
        yield row


def _check_coordinates(path: Path, linenos: np.ndarray, xy: np.ndarray) -> None:
    """Refuse positions ``xy`` (N, 2) metres beyond ``MAX_ABS_COORDINATE_M`` (naming the first such line)."""
    far = np.any(np.abs(xy) > MAX_ABS_COORDINATE_M, axis=1)
    if np.any(far):
        lineno = int(linenos[int(np.argmax(far))])
        raise PoseFileError(f"{path}:{lineno}: position {xy[int(np.argmax(far))].tolist()} is more than "
                            f"{MAX_ABS_COORDINATE_M:.0e} m from the origin; positions must be metres in a map or "
                            f"UTM frame")


def read_boreas_radar_poses(path: str | Path, time_unit: str | None = None) -> PoseSequence:
    """Read a Boreas ``applanix/radar_poses.csv`` (GPSTime, easting, northing, heading).

    Args:
        time_unit: unit of GPSTime (``s``, ``ms``, ``us``, ``ns``). None: the published files are absolute UTC
            times in ns or µs, told apart by magnitude; relative times are refused (``gps_time_to_us``).
    """
    path = Path(path)
    def columns(header: list[str] | None) -> tuple[int, list[int]]:
        idx = {name: i for i, name in enumerate(header or BOREAS_COLUMNS)}
        for need in ("GPSTime", "easting", "northing", "heading"):
            if need not in idx:
                raise PoseFileError(f"{path}:1: header lacks column {need!r}")
        return idx["GPSTime"], [idx["easting"], idx["northing"], idx["heading"]]

    table = _read_table(path, 10, "GPSTime", f"a Boreas radar_poses.csv: {','.join(BOREAS_COLUMNS)}", columns)
    t_raw, vals = table.times, table.values
    t_us = gps_time_to_us(t_raw, time_unit, f"{path}: GPSTime")
    _check_coordinates(path, table.linenos, vals[:, :2])
    _refuse_repeated_times(t_us, path)
    # the format's heading is radians; degrees within +-2 pi built a map 135 degrees off (QA, session 24)
    _refuse_degrees_in_plain_yaw(path, t_us, vals[:, :2], vals[:, 2], "heading",
                                 fix="a Boreas radar_poses.csv holds its heading in radians: convert the column")
    _refuse_heading_off_travel(path, t_us, vals[:, :2], vals[:, 2], "heading column",
                               "a Boreas heading is radians counter-clockwise from east (a compass heading, clockwise "
                               "from north, is pi/2 - heading)")
    return PoseSequence(t_us, vals[:, :2], vals[:, 2])


def write_boreas_radar_poses(poses: PoseSequence, path: str | Path) -> Path:
    """Write poses as a Boreas ``radar_poses.csv`` (GPSTime in microseconds; unknown columns zero)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(BOREAS_COLUMNS)
        for t, (x, y), yaw in zip(poses.timestamps_us, poses.xy, poses.yaw, strict=True):
            w.writerow([int(t), repr(float(x)), repr(float(y)), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                        repr(float(yaw)), 0.0, 0.0, 0.0])
    return path


def read_mulran_global_pose(path: str | Path, time_unit: str | None = None) -> PoseSequence:
    """Read MulRan ``global_pose.csv``: timestamp then a 3x4 row-major [R|t] matrix, no header.

    Args:
        time_unit: unit of the timestamp column. None = nanoseconds, the format's unit; a file whose values
            are absolute UTC times in another unit (e.g. µs) is refused rather than read 1000x off.
    """
    path = Path(path)
    table = _read_table(path, 13, None, "a MulRan global_pose.csv: timestamp, then a 3x4 [R|t] matrix row by row",
                        lambda _: (0, list(range(1, 13))))
    t_raw, m = table.times, table.values
    if time_unit is None:
        found = absolute_time_unit(t_raw)
        if found is not None and found != "ns":
            # 1e12 is absolute ms (2001) or a relative ns clock from 1,000 s: say both (QA, session 24)
            raise PoseFileError(f"{path}: MulRan timestamps are nanoseconds, but these read as absolute times in "
                                f"{found}; give the unit explicitly: --time-unit {found} if they are, --time-unit ns "
                                "if they are a relative clock in the format's nanoseconds")
        time_unit = "ns"
    _check_coordinates(path, table.linenos, m[:, [3, 7]])
    yaw = np.arctan2(m[:, 4], m[:, 0])  # R[1,0], R[0,0]
    t_us = to_microseconds(t_raw, time_unit)
    _refuse_repeated_times(t_us, path)
    _refuse_heading_off_travel(path, t_us, m[:, [3, 7]], yaw, "rotation",
                               "each row is a 3x4 [R|t] matrix written row by row (R transposed, i.e. written column "
                               "by column, turns every heading the other way)")
    return PoseSequence(t_us, m[:, [3, 7]], yaw)


def write_mulran_global_pose(poses: PoseSequence, path: str | Path) -> Path:
    """Write MulRan ``global_pose.csv`` (timestamp ns + 3x4 row-major matrix, z = 0)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    c, s = np.cos(poses.yaw), np.sin(poses.yaw)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        for i in range(len(poses)):
            x, y = poses.xy[i]
            w.writerow([int(poses.timestamps_us[i]) * 1000, c[i], -s[i], 0.0, x, s[i], c[i], 0.0, y,
                        0.0, 0.0, 1.0, 0.0])
    return path


def read_txyyaw_csv(path: str | Path, time_unit: str | None = None) -> PoseSequence:
    """Read a plain CSV with columns ``t,x,y,yaw`` (x/y metres, header optional).

    The time unit comes from ``time_unit``, else from the header (``t_s``, ``t_ms``, ``t_us``, ``t_ns``),
    else from absolute UTC times (``absolute_time_unit``); relative times without a unit are refused.
    The yaw (counter-clockwise from +x) is in radians, or in degrees when the header names the column
    ``yaw_deg`` (``yaw_rad`` states radians). A plain ``yaw`` column, or a file without a header, whose values
    exceed 2 pi in magnitude is refused (almost surely degrees: name the column ``yaw_deg``).

    Raises:
        PoseFileError: malformed rows, an unknown yaw column name, a plain yaw beyond 2 pi, a position beyond
        ``MAX_ABS_COORDINATE_M``, or a time unit that cannot be told (the message says what to pass).
    """
    path = Path(path)
    if not path.is_file():
        raise PoseFileError(_missing_pose_file(path))
    with path.open(newline="", encoding="utf-8-sig") as fh:
        first = next(_csv_rows(path, fh), [""])
    head = first[0].strip().lower() if first else ""
    header_unit = TXYYAW_TIME_HEADERS.get(head)
    if head not in TXYYAW_TIME_HEADERS and not _is_number(head):
        raise PoseFileError(f"{path}:1: the first column is named {first[0].strip()!r}, which is not a time column "
                            f"name this reader knows; name it t_s, t_ms, t_us or t_ns by the unit of its values (or t "
                            "for absolute UTC times), then x, y (metres) and yaw, yaw_rad or yaw_deg, e.g. the "
                            "header line t_s,x,y,yaw")
    table = _read_table(path, 4, first[0].strip() if head in TXYYAW_TIME_HEADERS else None, "t,x,y,yaw",
                        lambda _: (0, [1, 2, 3]))
    header = table.header
    if time_unit is not None and header_unit is not None and _check_unit(time_unit) != header_unit:
        raise PoseFileError(f"{path}:1: the header names the time column {first[0].strip()!r} ({header_unit}), but "
                            f"the time unit given is {time_unit!r}: drop --time-unit, or rename the column "
                            f"t_{_check_unit(time_unit)} (or t) if the values are in {time_unit}")
    yaw_header = header[3] if header is not None and len(header) > 3 else None
    yaw_name = yaw_header.lower() if yaw_header is not None else None
    if yaw_name is not None and yaw_name not in TXYYAW_YAW_HEADERS:
        raise PoseFileError(f"{path}:1: the 4th column is named {yaw_header!r}; name it yaw_deg (degrees), "
                            f"yaw_rad or yaw (radians)")
    t_raw, vals = table.times, table.values
    _check_coordinates(path, table.linenos, vals[:, 0:2])
    yaw = vals[:, 2]
    if yaw_name == "yaw_deg":
        yaw = np.radians(yaw)
    elif yaw_name in (None, "yaw"):
        beyond = np.abs(yaw) > _MAX_PLAIN_YAW_RAD
        if np.any(beyond):
            i = int(np.argmax(beyond))
            raise PoseFileError(
                f"{path}:{int(table.linenos[i])}: yaw {yaw[i]:g} is beyond 2 pi, but a plain yaw column (or one without a "
                f"header) is read as radians; these look like degrees: name the column yaw_deg in a header line "
                f"(e.g. t_us,x,y,yaw_deg), or yaw_rad if they really are radians")
    t_name = first[0].strip() if header is not None else "t"
    if header_unit is not None:  # (an explicit unit other than the header's was refused above)
        absolute = absolute_time_unit(t_raw)
        if absolute is not None and absolute != header_unit:
            raise PoseFileError(f"{path}: column {t_name!r} declares {header_unit}, but its values are absolute UTC "
                                f"times in {absolute}: rename the column t_{absolute} (or t, whose unit then follows "
                                "from the values)")
    t_us = gps_time_to_us(t_raw, time_unit or header_unit, f"{path}: column {t_name}")
    _refuse_repeated_times(t_us, path)
    if yaw_name in (None, "yaw"):
        _refuse_degrees_in_plain_yaw(path, t_us, vals[:, 0:2], yaw, yaw_header or "yaw (no header)")
    _refuse_heading_off_travel(path, t_us, vals[:, 0:2], yaw, "yaw column",
                               "yaw is counter-clockwise from +x (a compass heading, clockwise from north, is "
                               "pi/2 - yaw)")
    return PoseSequence(t_us, vals[:, 0:2], yaw)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


#: a stretch of at least this much path (metres) is one step when the yaw is compared with the direction of travel
_MOVING_STEP_M = 0.5
#: ... and it counts as moving when its end points lie at least this share of it apart (GNSS jitter while standing
#: adds path but no displacement)
_MOVING_CHORD_SHARE = 0.8
#: the yaw matches the direction of travel when the median |yaw - travel direction| is below this, degrees ...
_YAW_MATCH_DEG = 10.0
#: ... and does not when it is above this
_YAW_MISMATCH_DEG = 45.0
#: moving steps it takes to compare (fewer: no verdict)
_MIN_MOVING_STEPS = 3


def travel_yaw_mismatch_deg(xy: np.ndarray, yaw_rad: np.ndarray) -> float | None:
    """Median |yaw - direction of travel| in degrees over the moving stretches of a trajectory.

    Every pose is paired with the first later pose at least ``_MOVING_STEP_M`` of path on, whatever the pose
    rate: row to row, a 20 Hz file below 36 km/h or a 100 Hz INS file never moves 0.5 m, and a guard on single
    rows gave no verdict (QA, session 24: degrees in a plain yaw column at 20 Hz were read as radians, the map
    225 degrees off).

    Args:
        xy: (N, 2) positions, metres, in time order. yaw_rad: (N,) headings, radians.

    Returns:
        The median (0..180 degrees; a median, so rare reversing stretches do not sway it), or None when fewer
        than ``_MIN_MOVING_STEPS`` stretches move.
    """
    stretches = _moving_stretches(xy, yaw_rad)
    if stretches is None:
        return None
    heading, travel = stretches
    return float(np.degrees(np.median(np.abs(wrap_angle(heading - travel)))))


def _moving_stretches(xy: np.ndarray, yaw_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(heading, direction of travel), radians, over every stretch of ``_MOVING_STEP_M`` of path that moves (see
    ``travel_yaw_mismatch_deg``); None when fewer than ``_MIN_MOVING_STEPS`` stretches move."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    yaw = np.asarray(yaw_rad, np.float64).reshape(-1)
    if len(xy) < 2:
        return None
    path = _path_m(xy)
    end = np.searchsorted(path, path + _MOVING_STEP_M, side="left")
    start = np.flatnonzero(end < len(xy))
    moving, travel, heading = _chords(xy, yaw, start, end[start], _MOVING_STEP_M)
    if int(moving.sum()) < _MIN_MOVING_STEPS:
        return None
    return heading[moving], travel[moving]


def _path_m(xy: np.ndarray) -> np.ndarray:
    """(N,) path length driven up to each of the (N, 2) positions, metres (0 at the first)."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])


def _chords(xy: np.ndarray, yaw: np.ndarray, start: np.ndarray, end: np.ndarray, path_m: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each chord from pose ``start[i]`` to pose ``end[i]`` over ``path_m`` of path: (it moves, i.e. spans at
    least ``_MOVING_CHORD_SHARE`` of that path; its direction of travel; its heading, the circular mean of its end
    points' yaws), radians."""
    step = xy[end] - xy[start]
    moves = np.linalg.norm(step, axis=1) >= _MOVING_CHORD_SHARE * path_m
    a, b = yaw[start], yaw[end]
    return moves, np.arctan2(step[:, 1], step[:, 0]), np.arctan2(np.sin(a) + np.sin(b), np.cos(a) + np.cos(b))


#: ``_refuse_heading_off_travel``: a sensor's heading keeps one angle to the direction of travel (its mounting; a
#: reversal folds onto it), so the resultant length of 2 x (heading - travel) stays near 1 (the real Boreas drives:
#: 0.997-0.999); a compass heading (pi/2 - yaw) or a transposed rotation (-yaw) falls to 0.3-0.5 on a drive that
#: turns. The check needs the drive to turn (resultant of 2 x travel below ``_TURNING_DRIVE``).
_STEADY_HEADING = 0.8
_TURNING_DRIVE = 0.95


#: ``_turn_sense``: the path is sampled every this many metres; a turn between two chords counts when the direction
#: of travel changes by ``_TURN_MIN_DEG``-``_TURN_MAX_DEG`` (more: a reversal, where travel flips and heading does
#: not), and the sense is judged once the counted turns add up to ``_TURN_TOTAL_DEG``.
_TURN_SAMPLE_M = 5.0
_TURN_MIN_DEG, _TURN_MAX_DEG, _TURN_TOTAL_DEG = 10.0, 120.0, 60.0


def _turn_sense(xy: np.ndarray, yaw: np.ndarray) -> tuple[float, float] | None:
    """(heading change / travel-direction change, least squares over the drive's turns; the turns' total in degrees)
    of a trajectory in time order: about +1 when the heading turns with the vehicle, forward or in reverse, whatever
    its mounting angle; about -1 for a mirrored convention (a compass heading, a negated yaw, a transposed
    rotation). None when the drive turns less than ``_TURN_TOTAL_DEG``."""
    path = _path_m(xy)
    if path[-1] < 3 * _TURN_SAMPLE_M:
        return None
    idx = np.unique(np.searchsorted(path, np.arange(0.0, path[-1], _TURN_SAMPLE_M)))
    ok, travel, heading = _chords(xy, yaw, idx[:-1], idx[1:], _TURN_SAMPLE_M)
    pair = ok[:-1] & ok[1:]
    d_travel = wrap_angle(np.diff(travel))[pair]
    d_heading = wrap_angle(np.diff(heading))[pair]
    turn = (np.abs(d_travel) >= np.radians(_TURN_MIN_DEG)) & (np.abs(d_travel) <= np.radians(_TURN_MAX_DEG))
    total = float(np.degrees(np.abs(d_travel[turn]).sum()))
    if total < _TURN_TOTAL_DEG:
        return None
    return float((d_heading[turn] * d_travel[turn]).sum() / (d_travel[turn] ** 2).sum()), total


def _refuse_heading_off_travel(path: Path, t_us: np.ndarray, xy: np.ndarray, yaw: np.ndarray, what: str,
                               fix: str) -> None:
    """Refuse headings that do not keep one angle to the direction of travel on a drive that turns, or that turn
    against it: another angle convention (a compass heading, clockwise from north) or a rotation read transposed
    (QA session 38: both built maps whose every keyframe was turned, without a word; QA session 40: on a route of
    right-angle streets both keep a steady angle modulo 180 degrees - the heading turns the other way at every
    corner, which ``_turn_sense`` reads)."""
    order = np.argsort(t_us, kind="stable")
    stretches = _moving_stretches(xy[order], yaw[order])
    if stretches is None:
        return
    heading, travel = stretches
    steady = float(np.abs(np.mean(np.exp(2j * (heading - travel)))))
    turning = float(np.abs(np.mean(np.exp(2j * travel))))
    if steady < _STEADY_HEADING and turning < _TURNING_DRIVE:
        raise PoseFileError(f"{path}: the {what} does not follow the direction of travel (steadiness {steady:.2f}, "
                            f"1 = a fixed mounting angle; a real drive keeps above 0.99): {fix}")
    sense = _turn_sense(np.asarray(xy, np.float64)[order], np.asarray(yaw, np.float64)[order])
    if sense is not None and sense[0] < 0.0:
        raise PoseFileError(f"{path}: the {what} turns against the direction of travel (heading change / travel "
                            f"change {sense[0]:.2f} over {sense[1]:.0f} deg of turns; a real drive's is about +1): "
                            f"{fix}")


def _refuse_degrees_in_plain_yaw(path: Path, t_us: np.ndarray, xy: np.ndarray, yaw: np.ndarray, column: str,
                                 fix: str = "name the column yaw_deg in a header line (e.g. t_s,x,y,yaw_deg), or "
                                            "yaw_rad if they really are radians") -> None:
    """Refuse a yaw column read as radians (a plain ``yaw``, a Boreas ``heading``) whose values, read as degrees,
    follow the direction of travel while, read as radians, they do not: degrees within +-2 pi (e.g. a road at 4
    degrees). ``fix``: what the message tells the user to do."""
    order = np.argsort(t_us, kind="stable")
    as_rad = travel_yaw_mismatch_deg(xy[order], yaw[order])
    as_deg = travel_yaw_mismatch_deg(xy[order], np.radians(yaw[order]))
    if as_rad is None or as_deg is None:
        return
    # read as radians about 180 degrees off the travel: a drive wholly in reverse, not degrees (QA re-test, session 23)
    if as_deg < _YAW_MATCH_DEG and _YAW_MISMATCH_DEG < as_rad < 180.0 - _YAW_MATCH_DEG:
        raise PoseFileError(
            f"{path}: the {column} column is read as radians, but its values follow the direction of travel only "
            f"as degrees (median difference {as_deg:.1f} deg as degrees, {as_rad:.1f} deg as radians): {fix}")


def write_txyyaw_csv(poses: PoseSequence, path: str | Path) -> Path:
    """Write a plain ``t_s,x,y,yaw`` CSV (t seconds, declared in the header; metres, radians)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t_s", "x", "y", "yaw"])
        for t, (x, y), yaw in zip(poses.timestamps_us, poses.xy, poses.yaw, strict=True):
            w.writerow([f"{t / 1e6:.6f}", repr(float(x)), repr(float(y)), repr(float(yaw))])
    return path


def read_poses(path: str | Path, time_unit: str | None = None) -> PoseSequence:
    """Read any supported pose file, choosing the reader from its first line.

    Args:
        time_unit: unit of the file's timestamps (``s``, ``ms``, ``us``, ``ns``); None: see the module
            docstring (absolute UTC times or the format's own unit; relative times are refused).
    """
    path = Path(path)
    if not path.is_file():
        raise PoseFileError(_missing_pose_file(path))
    try:
        with path.open(encoding="utf-8-sig") as fh:
            first = fh.readline().strip()
        head = first.split(",")[0].strip().lower()
        if head == "gpstime":
            return read_boreas_radar_poses(path, time_unit)
        if head in TXYYAW_TIME_HEADERS or len(first.split(",")) == 4:
            return read_txyyaw_csv(path, time_unit)
        if len(first.split(",")) >= 13:
            return read_mulran_global_pose(path, time_unit)
    except UnicodeDecodeError:
        with path.open("rb") as fh:
            bom = fh.read(2)
        if bom in (b"\xff\xfe", b"\xfe\xff"):  # QA session 40: Windows PowerShell 5 writes UTF-16 by default
            raise PoseFileError(f"{path}: UTF-16 text; save the pose file as UTF-8 (e.g. PowerShell: Out-File "
                                "-Encoding utf8)") from None
        raise PoseFileError(f"{path}: not a text pose file (binary data); expected a Boreas, MulRan or "
                            "t,x,y,yaw CSV") from None
    if path.stat().st_size == 0:  # QA session 40: "unrecognised format" for an empty file
        raise PoseFileError(f"{path}: empty file (0 bytes); expected a Boreas, MulRan or t,x,y,yaw CSV")
    raise PoseFileError(f"{path}:1: unrecognised pose file format (expected Boreas, MulRan or t,x,y,yaw CSV)")
