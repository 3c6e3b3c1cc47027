"""Pose files: Boreas ``applanix/radar_poses.csv``, MulRan ``global_pose.csv`` and a plain ``t,x,y,yaw`` CSV.

All readers return a ``PoseSequence`` of planar poses T_world_sensor in metres / radians with int64
microsecond timestamps. Malformed files raise ``PoseFileError`` naming the file and the 1-based line.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from reradar_core.errors import PoseFileError
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
]

BOREAS_COLUMNS = (
    "GPSTime,easting,northing,altitude,vel_east,vel_north,vel_up,roll,pitch,heading,angvel_z,angvel_y,angvel_x"
).split(",")


@dataclass
class PoseSequence:
    """Planar poses T_world_sensor along a trajectory.

    Attributes:
        timestamps_us: (N,) int64 UTC microseconds, strictly increasing after ``sorted()``.
        xy: (N, 2) float64 metres in the world (map) frame, x east / y north for GNSS data.
        yaw: (N,) float64 radians, counter-clockwise from world +x, wrapped to (-pi, pi].
    """

    timestamps_us: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray

    def __post_init__(self) -> None:
        self.timestamps_us = np.asarray(self.timestamps_us, dtype=np.int64).reshape(-1)
        self.xy = np.asarray(self.xy, dtype=np.float64).reshape(-1, 2)
        self.yaw = wrap_angle(np.asarray(self.yaw, dtype=np.float64).reshape(-1))
        n = len(self.timestamps_us)
        if self.xy.shape[0] != n or self.yaw.shape[0] != n:
            raise PoseFileError(f"pose arrays disagree in length: {n}, {self.xy.shape[0]}, {self.yaw.shape[0]}")

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

    def interpolate(self, t_us: np.ndarray | int) -> np.ndarray:
        """Poses at times ``t_us`` by linear interpolation (yaw on the circle), clamped at the ends.

        Returns:
            (..., 3) float64 (x, y, yaw) with the shape of ``t_us`` plus a trailing 3.
        """
        t = np.asarray(t_us, dtype=np.float64)
        ts = self.timestamps_us.astype(np.float64)
        x = np.interp(t, ts, self.xy[:, 0])
        y = np.interp(t, ts, self.xy[:, 1])
        yaw_unwrapped = np.unwrap(self.yaw)
        yaw = wrap_angle(np.interp(t, ts, yaw_unwrapped))
        return np.stack([x, y, yaw], axis=-1)

    def path_length_m(self) -> float:
        return float(np.sum(np.linalg.norm(np.diff(self.xy, axis=0), axis=1)))


def gps_time_to_us(values: np.ndarray) -> np.ndarray:
    """Convert Boreas GPSTime values to int64 microseconds, detecting the unit by magnitude.

    The published files differ: some store nanoseconds (~1.6e18), others microseconds (~1.6e15);
    plain seconds (~1.6e9) are accepted too.
    """
    v = np.asarray(values)
    mag = float(np.nanmax(np.abs(v.astype(np.float64)))) if v.size else 0.0
    if mag > 1e17:
        return (v.astype(np.int64) // 1000).astype(np.int64)
    if mag > 1e14:
        return v.astype(np.int64)
    return np.round(v.astype(np.float64) * 1e6).astype(np.int64)


def _read_rows(path: Path, min_cols: int, header_first: str | None) -> tuple[list[str] | None, list[tuple[int, list[str]]]]:
    if not path.is_file():
        raise PoseFileError(f"{path}: no such pose file")
    rows: list[tuple[int, list[str]]] = []
    header = None
    with path.open(newline="") as fh:
        for lineno, row in enumerate(csv.reader(fh), start=1):
            if not row or all(not c.strip() for c in row):
                continue
            if lineno == 1 and header_first is not None and row[0].strip().lower() == header_first.lower():
                header = [c.strip() for c in row]
                continue
            if len(row) < min_cols:
                raise PoseFileError(f"{path}:{lineno}: expected at least {min_cols} columns, got {len(row)}")
            rows.append((lineno, row))
    if not rows:
        raise PoseFileError(f"{path}: no pose rows")
    return header, rows


def _parse_floats(path: Path, rows: list[tuple[int, list[str]]], cols: list[int]) -> np.ndarray:
    out = np.empty((len(rows), len(cols)), dtype=np.float64)
    for i, (lineno, row) in enumerate(rows):
        try:
            vals = [float(row[c]) for c in cols]
        except (ValueError, IndexError):
            raise PoseFileError(f"{path}:{lineno}: non-numeric value in {row[:max(cols) + 1]}") from None
        if not np.all(np.isfinite(vals)):
            raise PoseFileError(f"{path}:{lineno}: NaN or infinite value")
        out[i] = vals
    return out


def _parse_int_column(path: Path, rows: list[tuple[int, list[str]]], col: int) -> np.ndarray:
    out = np.empty(len(rows), dtype=np.int64)
    for i, (lineno, row) in enumerate(rows):
        txt = row[col].strip()
        try:
            out[i] = int(txt)
        except ValueError:
            try:
                out[i] = int(round(float(txt) * 1e6)) if "." in txt or "e" in txt.lower() else int(txt)
            except ValueError:
                raise PoseFileError(f"{path}:{lineno}: timestamp {txt!r} is not a number") from None
    return out


def read_boreas_radar_poses(path: str | Path) -> PoseSequence:
    """Read a Boreas ``applanix/radar_poses.csv`` (GPSTime in ns or us, easting, northing, heading)."""
    path = Path(path)
    header, rows = _read_rows(path, 10, "GPSTime")
    idx = {name: i for i, name in enumerate(header or BOREAS_COLUMNS)}
    for need in ("GPSTime", "easting", "northing", "heading"):
        if need not in idx:
            raise PoseFileError(f"{path}:1: header lacks column {need!r}")
    raw_t = [r[idx["GPSTime"]].strip() for _, r in rows]
    if any("." in t for t in raw_t):
        t_vals = _parse_floats(path, rows, [idx["GPSTime"]])[:, 0]
        t_us = gps_time_to_us(t_vals)
    else:
        t_us = gps_time_to_us(_parse_int_column(path, rows, idx["GPSTime"]))
    vals = _parse_floats(path, rows, [idx["easting"], idx["northing"], idx["heading"]])
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


def read_mulran_global_pose(path: str | Path) -> PoseSequence:
    """Read MulRan ``global_pose.csv``: timestamp (ns) then a 3x4 row-major [R|t] matrix, no header."""
    path = Path(path)
    _, rows = _read_rows(path, 13, None)
    t_ns = _parse_int_column(path, rows, 0)
    m = _parse_floats(path, rows, list(range(1, 13)))
    yaw = np.arctan2(m[:, 4], m[:, 0])  # R[1,0], R[0,0]
    return PoseSequence(t_ns // 1000, m[:, [3, 7]], yaw)


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


def read_txyyaw_csv(path: str | Path) -> PoseSequence:
    """Read a plain CSV with columns ``t,x,y,yaw`` (t seconds, x/y metres, yaw radians; header optional)."""
    path = Path(path)
    _, rows = _read_rows(path, 4, "t")
    vals = _parse_floats(path, rows, [0, 1, 2, 3])
    return PoseSequence(np.round(vals[:, 0] * 1e6).astype(np.int64), vals[:, 1:3], vals[:, 3])


def write_txyyaw_csv(poses: PoseSequence, path: str | Path) -> Path:
    """Write a plain ``t,x,y,yaw`` CSV (t seconds, metres, radians)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "x", "y", "yaw"])
        for t, (x, y), yaw in zip(poses.timestamps_us, poses.xy, poses.yaw, strict=True):
            w.writerow([f"{t / 1e6:.6f}", repr(float(x)), repr(float(y)), repr(float(yaw))])
    return path


def read_poses(path: str | Path) -> PoseSequence:
    """Read any supported pose file, choosing the reader from its first line."""
    path = Path(path)
    if not path.is_file():
        raise PoseFileError(f"{path}: no such pose file")
    with path.open() as fh:
        first = fh.readline().strip()
    head = first.split(",")[0].strip().lower()
    if head == "gpstime":
        return read_boreas_radar_poses(path)
    if head == "t" or len(first.split(",")) == 4:
        return read_txyyaw_csv(path)
    if len(first.split(",")) >= 13:
        return read_mulran_global_pose(path)
    raise PoseFileError(f"{path}:1: unrecognised pose file format (expected Boreas, MulRan or t,x,y,yaw CSV)")
