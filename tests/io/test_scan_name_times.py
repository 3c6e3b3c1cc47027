"""A scan's file name (the time its pose is taken at) and the time it carries (its first azimuth's, columns 0-7:
the map's keyframe time) must be one instant: ``load_sequence`` refuses a folder where they lie more than one
sweep apart, naming the file (basename) and both times. Tiny scans made by the tests; no real data needed."""

from __future__ import annotations

import logging
import shutil
import zlib

import cv2
import numpy as np
import pytest

from reradar_core.errors import DatasetError, ScanFormatError
from reradar_core.io.datasets import (
    check_scan_name_times,
    load_sequence,
    scan_path,
    write_sequence_poses,
    write_sequence_scan,
)
from reradar_core.io.poses import PoseSequence
from reradar_core.io.presets import get_preset
from reradar_core.io.scan import (
    RadarScan,
    encode_navtech_png_bytes,
    navtech_png_first_time_us,
    read_navtech_png,
)

T0 = 1_547_131_046_353_776  # an Oxford-like time (µs); bytes with carries under PNG's Sub / Average filters
SWEEP_US = 250_000  # the oxford preset's sweep period
STEP_US = 625  # 250 ms / 400 azimuths


def _scan(t0_us: int, value: float = 0.5) -> RadarScan:
    """400 azimuths x 32 range bins (a scan cropped in range fits the oxford preset), first azimuth at ``t0_us``."""
    return RadarScan.from_power(np.full((400, 32), value, np.float32), "oxford", start_time_us=t0_us)


def _track(times_us: list[int]) -> PoseSequence:
    t = np.asarray(times_us, dtype=np.int64)
    s = (t - t[0]) / 1e6
    return PoseSequence(t, np.column_stack([10.0 * s, 0.0 * s]), 0.0 * s)


def _folder(tmp_path, layout: str = "oxford", n: int = 3):
    """A consistent sequence: scan k named by its first azimuth's time, T0 + k sweeps."""
    root = tmp_path / "seq"
    times = [T0 + k * SWEEP_US for k in range(n)]
    for k, t in enumerate(times):
        write_sequence_scan(root, layout, _scan(t, (k + 1) / 255.0))
    write_sequence_poses(root, layout, _track(times))
    return root, times


def test_a_folder_whose_names_are_the_first_azimuths_times_loads(tmp_path):
    root, times = _folder(tmp_path)
    seq = load_sequence(root, preset="oxford")
    assert seq.timestamps_us.tolist() == times
    for i, t in enumerate(times):
        assert navtech_png_first_time_us(seq.scan_paths[i]) == t
        assert seq.load_scan(i).timestamp_us == t


def test_a_scan_renamed_to_another_time_is_refused_naming_the_folder_the_file_and_both_times(tmp_path):
    root, times = _folder(tmp_path)
    # scan 2 carries a time 0.6 s (more than two sweeps) before its name's, which no other scan carries
    renamed = scan_path(root, "oxford", times[2])
    renamed.write_bytes(encode_navtech_png_bytes(_scan(times[2] - 600_000)))
    with pytest.raises(DatasetError) as err:
        load_sequence(root, preset="oxford")
    msg = str(err.value)
    assert msg.startswith(f"{renamed.parent}: scan {times[2]}.png: its file name gives the time {times[2]} us")
    assert f"say {times[2] - 600_000} us, 0.6 s earlier" in msg and "more than one sweep (0.25 s)" in msg
    assert f"rename it to {times[2] - 600_000}.png" in msg and "remove it from the folder" in msg


@pytest.mark.parametrize("offset_us", [500_000, 200_000])
def test_a_copy_of_a_scan_is_refused_as_a_copy(tmp_path, offset_us):
    """A copy carries its original's time: the map keys keyframes by it, so the map would be unreadable - refused
    also when its name lies within a sweep of that time (the name check alone passes it: QA, session 25)."""
    root, times = _folder(tmp_path)
    copy = scan_path(root, "oxford", times[0] + offset_us)
    if copy.exists():
        copy.unlink()
    shutil.copy(scan_path(root, "oxford", times[0]), copy)
    with pytest.raises(DatasetError, match=rf"^{root}.*: scans {times[0]}\.png and {copy.stem}\.png carry the same "
                                           rf"scan time, {times[0]} us .*remove the copy"):
        load_sequence(root, preset="oxford")


def test_two_names_of_one_time_are_refused(tmp_path):
    root, times = _folder(tmp_path)
    twin = scan_path(root, "oxford", times[1]).with_name(f"00{times[1]}.png")
    twin.write_bytes(scan_path(root, "oxford", times[1]).read_bytes())
    with pytest.raises(DatasetError, match=rf"scans (00)?{times[1]}\.png and (00)?{times[1]}\.png are named by one "
                                           rf"time, {times[1]} us; keep one of them"):
        load_sequence(root, preset="oxford")


def test_the_tolerance_is_one_sweep_period_either_way(tmp_path):
    p = get_preset("oxford")
    for name_minus_embedded, ok in ((SWEEP_US, True), (-SWEEP_US, True), (SWEEP_US + 1, False),
                                    (-SWEEP_US - 1, False)):
        d = tmp_path / str(name_minus_embedded)
        path = d / f"{T0 + name_minus_embedded}.png"
        d.mkdir()
        path.write_bytes(encode_navtech_png_bytes(_scan(T0)))
        if ok:
            check_scan_name_times([path], np.asarray([T0 + name_minus_embedded]), p, "oxford")
        else:
            with pytest.raises(DatasetError, match=rf"scan {path.name}: .* say {T0} us"):
                check_scan_name_times([path], np.asarray([T0 + name_minus_embedded]), p, "oxford")


def test_names_of_another_azimuth_of_the_sweep_load_with_a_warning(tmp_path, caplog):
    """A dataset naming scans by its last (or middle) azimuth's time is a convention, not another instant: it
    loads, and the poses' first-azimuth assumption is pointed out once."""
    root, times = _folder(tmp_path)
    last = (400 - 1) * STEP_US
    for t in times:  # each scan now carries a first azimuth one sweep earlier: its name is the last azimuth's
        write_sequence_scan(root, "oxford", _scan(t - last)).rename(scan_path(root, "oxford", t))
    with caplog.at_level(logging.WARNING, logger="reradar_core.io.datasets"):
        seq = load_sequence(root, preset="oxford")
    assert seq.timestamps_us.tolist() == times
    assert seq.load_scan(1).timestamp_us == times[1] - last
    assert "3 of 3 scans are named by a time up to +249.4 ms from their first azimuth's time" in caplog.text


def test_a_folder_read_with_exact_names_logs_nothing(tmp_path, caplog):
    root, _ = _folder(tmp_path)
    with caplog.at_level(logging.WARNING, logger="reradar_core.io.datasets"):
        load_sequence(root, preset="oxford")
    assert "first azimuth" not in caplog.text


def test_every_disagreeing_scan_is_counted(tmp_path):
    root, times = _folder(tmp_path, n=4)
    for k in (1, 3):
        scan_path(root, "oxford", times[k]).write_bytes(encode_navtech_png_bytes(_scan(times[k] + 60_000_000)))
    with pytest.raises(DatasetError, match=rf"^{root}.*: scan {times[1]}\.png: .* 60 s later.*\(2 of 4 scans disagree so"):
        load_sequence(root, preset="oxford")


def test_mulran_nanosecond_names_are_compared_in_microseconds(tmp_path):
    root, times = _folder(tmp_path, layout="mulran")
    assert scan_path(root, "mulran", times[0]).name == f"{times[0] * 1000}.png"
    load_sequence(root, preset="mulran")  # ns names that agree load
    scan_path(root, "mulran", times[1]).write_bytes(encode_navtech_png_bytes(_scan(times[1] + 2_000_000)))
    with pytest.raises(DatasetError) as err:
        load_sequence(root, preset="mulran")
    msg = str(err.value)
    assert msg.startswith(f"{scan_path(root, 'mulran', times[1]).parent}: scan {times[1] * 1000}.png: its file name "
                          f"gives the time {times[1]} us (MulRan names are nanoseconds)")
    assert f"rename it to {(times[1] + 2_000_000) * 1000}.png" in msg


def test_boreas_layout_is_checked_too(tmp_path):
    root, times = _folder(tmp_path, layout="boreas")
    scan_path(root, "boreas", times[2]).write_bytes(encode_navtech_png_bytes(_scan(0)))  # a scan of time 0
    with pytest.raises(DatasetError, match=rf"scan {times[2]}\.png: .* say 0 us"):
        load_sequence(root, preset="oxford")


def test_a_scan_changed_after_loading_is_refused_when_read(tmp_path):
    root, times = _folder(tmp_path)
    seq = load_sequence(root, preset="oxford")
    scan_path(root, "oxford", times[1]).write_bytes(encode_navtech_png_bytes(_scan(times[1] - 5_000_000)))
    assert seq.load_scan(0).timestamp_us == times[0]
    with pytest.raises(DatasetError, match=rf"^{root}.*: scan {times[1]}\.png: .* 5 s earlier"):
        seq.load_scan(1)


def _chunk(kind: bytes, body: bytes) -> bytes:
    return len(body).to_bytes(4, "big") + kind + body + zlib.crc32(kind + body).to_bytes(4, "big")


def _png(raw: np.ndarray, kind: int, idat_bytes: int = 7, extra_chunks: int = 1) -> bytes:
    """``raw`` (uint8 (H, W)) as a greyscale PNG whose every row uses PNG filter ``kind`` (0 None, 1 Sub, 2 Up,
    3 Average, 4 Paeth), its image data split into ``idat_bytes``-byte IDAT chunks after ``extra_chunks`` tEXt
    chunks."""
    h, w = raw.shape
    prev = np.zeros(w, np.int64)
    rows = []
    for row in raw.astype(np.int64):
        out = []
        for x in range(w):
            a = int(row[x - 1]) if x else 0
            b = int(prev[x])
            c = int(prev[x - 1]) if x else 0
            if kind == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pred = a if pa <= pb and pa <= pc else b if pb <= pc else c
            else:
                pred = [0, a, b, (a + b) // 2][kind]
            out.append((int(row[x]) - pred) & 0xFF)
        rows.append(bytes([kind, *out]))
        prev = row
    data = zlib.compress(b"".join(rows))
    head = w.to_bytes(4, "big") + h.to_bytes(4, "big") + bytes([8, 0, 0, 0, 0])
    idat = b"".join(_chunk(b"IDAT", data[i:i + idat_bytes]) for i in range(0, len(data), idat_bytes))
    text = b"".join(_chunk(b"tEXt", b"Comment\x00%d" % i) for i in range(extra_chunks))
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", head) + text + idat + _chunk(b"IEND", b"")


def _raw(t0_us: int, rows: int = 400, cols: int = 11 + 32) -> np.ndarray:
    raw = cv2.imdecode(np.frombuffer(encode_navtech_png_bytes(_scan(t0_us)), np.uint8), cv2.IMREAD_UNCHANGED)
    return raw[:rows, :cols].copy()


@pytest.mark.parametrize("kind", [0, 1, 2, 3, 4])
def test_the_first_rows_time_is_read_under_every_png_filter(tmp_path, kind):
    raw = _raw(T0, rows=4, cols=24)
    path = tmp_path / "s.png"
    path.write_bytes(_png(raw, kind))
    assert np.array_equal(cv2.imdecode(np.frombuffer(path.read_bytes(), np.uint8), cv2.IMREAD_UNCHANGED), raw)
    assert navtech_png_first_time_us(path) == T0


def test_files_whose_first_row_cannot_be_read_cheaply_give_none(tmp_path):
    good = encode_navtech_png_bytes(_scan(T0))
    cases = {"16bit": cv2.imencode(".png", np.zeros((4, 24), np.uint16))[1].tobytes(),
             "colour": cv2.imencode(".png", np.zeros((4, 24, 3), np.uint8))[1].tobytes(),
             "cut": good[:60], "junk": b"not a png at all", "empty": b""}
    for name, data in cases.items():
        (tmp_path / f"{name}.png").write_bytes(data)
        assert navtech_png_first_time_us(tmp_path / f"{name}.png") is None, name
    (tmp_path / "folder.png").mkdir()
    assert navtech_png_first_time_us(tmp_path / "folder.png") is None


def test_a_scan_the_cheap_read_cannot_time_is_decoded_and_checked(tmp_path):
    """Hundreds of chunks before the image data: too many to walk, so the scan is decoded instead (and a
    mismatch is still refused)."""
    root, times = _folder(tmp_path)
    path = scan_path(root, "oxford", times[1])
    path.write_bytes(_png(_raw(times[1]), 1, idat_bytes=1 << 16, extra_chunks=300))
    assert navtech_png_first_time_us(path) is None and read_navtech_png(path, "oxford").timestamp_us == times[1]
    load_sequence(root, preset="oxford")
    path.write_bytes(_png(_raw(times[1] + 3_000_000), 1, idat_bytes=1 << 16, extra_chunks=300))
    with pytest.raises(DatasetError, match=rf"^{root}.*: scan {times[1]}\.png: .* 3 s later"):
        load_sequence(root, preset="oxford")


def test_a_scan_of_another_layout_is_left_to_the_reader(tmp_path):
    """A foreign image (no metadata columns) whose first pixels happen to read as a time: not reported as a name
    mismatch, but refused by the reader, which says what it is, when the scan is read."""
    root, times = _folder(tmp_path)
    rng = np.random.default_rng(0)
    foreign = rng.integers(0, 256, size=(400, 43), dtype=np.uint8)
    foreign[0, :8] = [10, 20, 30, 40, 50, 60, 5, 0]  # a positive int64 below 2^62, ~1.4e15 µs: not its name
    path = scan_path(root, "oxford", times[1])
    path.write_bytes(cv2.imencode(".png", foreign)[1].tobytes())
    assert navtech_png_first_time_us(path) == int(foreign[0, :8].view("<i8")[0])
    seq = load_sequence(root, preset="oxford")
    with pytest.raises(ScanFormatError, match="encoder column"):
        seq.load_scan(1)


def test_an_unreadable_file_is_left_to_the_reader(tmp_path):
    root, times = _folder(tmp_path)
    scan_path(root, "oxford", times[1]).write_bytes(b"not a png")
    seq = load_sequence(root, preset="oxford")
    with pytest.raises(ScanFormatError, match="not a readable PNG"):
        seq.load_scan(1)


def test_names_in_another_unit_are_said_to_be(tmp_path):
    """A folder named in nanoseconds (or a MulRan folder named in microseconds) is told so, not asked to rename
    every scan to a time 1.5e12 s away (QA, session 25)."""
    p = get_preset("oxford")
    path = tmp_path / f"{T0 * 1000}.png"
    path.write_bytes(encode_navtech_png_bytes(_scan(T0)))
    with pytest.raises(DatasetError, match="1000 times the time the scan carries .* the names look like nanoseconds"):
        check_scan_name_times([path], np.asarray([T0 * 1000]), p, "oxford")
    mul = tmp_path / "m" / f"{T0}.png"  # a MulRan name read as ns: T0 / 1000 us
    mul.parent.mkdir()
    mul.write_bytes(encode_navtech_png_bytes(_scan(T0)))
    with pytest.raises(DatasetError, match="1/1000 of the time the scan carries .* microseconds where this layout "
                                           "names scans in nanoseconds"):
        check_scan_name_times([mul], np.asarray([T0 // 1000]), get_preset("mulran"), "mulran")
