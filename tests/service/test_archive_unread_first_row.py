"""Scan archive members the upload's checks skipped (QA):

* a PNG whose first row the cheap reader cannot read (Adam7-interlaced - a legal file the build decodes - or one
  with hundreds of chunks before its image data) and whose name disagrees with its embedded time, or that is a
  copy of another member: the upload said 202 and the build failed later, where docs/SERVICE.md promises a 400
  before the 202. Such a PNG is now decoded as the build decodes it (only those: the others are timed from their
  first row) and checked alike; one the decoder refuses is still left to the build, which says why.
* a member named like a scan with a signed timestamp (``-1000000.png``) was silently left out of the map (5 of 6
  scans built, no note), where a sequence folder reads it as time -1 s and refuses it. Like a timestamp out of
  range, it is now a 400 naming the member; other names (a readme, macOS ``._`` files) are still ignored.
"""

from __future__ import annotations

import io
import sys
import tarfile
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from reradar_core.io.scan import PNG_SIGNATURE, navtech_png_first_time_us
from service.core.archive import check_scan_times, extract_scan_archive
from service.core.errors import BadRequestError

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_archive_scan_name_times import (  # noqa: E402
    LATER_US,
    TIMES,
    N,
    _client,
    _members,
    _nothing_kept,
    _png,
    _post,
    _wait_built,
    _with_chunks_before_image,
)

#: Adam7 passes: (first column, first row, column step, row step)
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))


def _interlaced(png: bytes) -> bytes:
    """``png`` (8-bit greyscale) re-encoded Adam7-interlaced: the same pixels, which OpenCV decodes, but whose
    first stored row is pass 1's (every 8th pixel), so the cheap first-row reader declines it."""
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image.dtype == np.uint8 and image.ndim == 2
    height, width = image.shape
    raw = b"".join(b"".join(b"\x00" + row.tobytes() for row in image[y0::dy, x0::dx])
                   for x0, y0, dx, dy in _ADAM7 if image[y0::dy, x0::dx].size)

    def chunk(kind: bytes, body: bytes) -> bytes:
        return len(body).to_bytes(4, "big") + kind + body + zlib.crc32(kind + body).to_bytes(4, "big")

    ihdr = width.to_bytes(4, "big") + height.to_bytes(4, "big") + bytes([8, 0, 0, 0, 1])
    out = PNG_SIGNATURE + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")
    decoded = cv2.imdecode(np.frombuffer(out, np.uint8), cv2.IMREAD_UNCHANGED)
    assert decoded is not None and np.array_equal(decoded, image)  # a legal PNG of the same scan
    return out


@pytest.fixture(params=["interlaced", "chunks-before-image"])
def unread(request: pytest.FixtureRequest, tmp_path: Path):  # type: ignore[no-untyped-def]
    """A re-encoding of a PNG that the build decodes but the cheap first-row read cannot time."""
    encode = _interlaced if request.param == "interlaced" else _with_chunks_before_image

    def make(png: bytes) -> bytes:
        data = encode(png)
        probe = tmp_path / "probe.png"
        probe.write_bytes(data)
        assert navtech_png_first_time_us(probe) is None
        return data

    return make


def test_a_member_the_first_row_read_cannot_time_is_refused_before_the_202(tmp_path: Path, unread) -> None:  # type: ignore[no-untyped-def]
    maps_dir = tmp_path / "maps"
    carried = TIMES[2] + LATER_US
    members = _members()
    members[f"{TIMES[2]}.png"] = unread(_png(2, carried))
    with _client(maps_dir) as client:
        r = _post(client, "renamed", members)
        assert r.status_code == 400, r.text
        detail = r.json()["detail"]
        assert detail.startswith(f"scan archive member {TIMES[2]}.png: its file name gives the time {TIMES[2]} us, "
                                 f"but the timestamps in the scan (columns 0-7, first azimuth) say {carried} us, "
                                 "3 s later"), detail
        assert f"rename it to {carried}.png" in detail
        _nothing_kept(client, maps_dir, "renamed")
        # a copy of another member (its time, another name) is said to be one
        members = _members()
        members[f"{TIMES[3] + 100_000_000}.png"] = unread(_png(1, TIMES[1]))
        r = _post(client, "copy", members)
        assert r.status_code == 400, r.text
        assert r.json()["detail"].startswith(f"scan archive members '{TIMES[1]}.png' and "
                                             f"'{TIMES[3] + 100_000_000}.png' carry the same scan time")
        _nothing_kept(client, maps_dir, "copy")
        # named by the time it carries, it builds
        members = _members()
        members[f"{TIMES[2]}.png"] = unread(_png(2, TIMES[2]))
        r = _post(client, "fine", members)
        assert r.status_code == 202, r.text
        info = _wait_built(client, "fine")
        assert info["state"] == "ready" and info["num_keyframes"] == N, info


def test_only_members_the_first_row_read_cannot_time_are_decoded(tmp_path: Path) -> None:
    paths = []
    for i, t in enumerate(TIMES):
        path = tmp_path / f"{t}.png"
        path.write_bytes(_png(i, t) if i != 1 else _interlaced(_png(i, t)))
        paths.append(path)
    decoded: list[Path] = []

    def decode(path: Path) -> int:
        decoded.append(path)
        return TIMES[paths.index(path)]

    check_scan_times(paths, "boreas", decode)
    assert decoded == [paths[1]]
    # one the decoder refuses is left to the build (which says why), as without a decoder
    paths[1].write_bytes(_interlaced(_png(1, TIMES[1] + LATER_US)))
    check_scan_times(paths, "boreas", lambda path: None)
    check_scan_times(paths, "boreas")


def _zip(members: dict[str, bytes]) -> bytes:
    import zipfile

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return buf.getvalue()


@pytest.mark.parametrize("name", ["-1000000.png", "+1000000.png", "-5.npy"])
def test_a_member_named_like_a_scan_with_a_signed_timestamp_is_400(tmp_path: Path, name: str) -> None:
    members = {**_members(), f"sub/{name}": _png(0, 1_000_000)}
    maps_dir = tmp_path / "maps"
    with _client(maps_dir) as client:
        r = _post(client, "signed", members)
        assert r.status_code == 400, r.text
        detail = r.json()["detail"]
        assert detail.startswith(f"scan archive member {name!r}: a scan's name must be its timestamp, digits only"), \
            detail
        assert "sub/" not in detail and str(tmp_path) not in detail
        _nothing_kept(client, maps_dir, "signed")
    # a tar says the same
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tf:
        for member, data in members.items():
            info = tarfile.TarInfo(member)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    archive = tmp_path / "scans.tar"
    archive.write_bytes(buf.getvalue())
    with pytest.raises(BadRequestError, match=rf"^scan archive member '\{name[0]}"):
        extract_scan_archive(archive, tmp_path / "out", 100, 1 << 30)


def test_other_members_are_still_ignored(tmp_path: Path) -> None:
    """A readme, a poses file and macOS resource files (``._<name>``) beside the scans are left out, as before."""
    members = {**_members(), "README.txt": b"scans", f"__MACOSX/._-{TIMES[0]}.png": b"\x00\x05\x16\x07",
               f"._{TIMES[1]}.png": b"\x00\x05\x16\x07", "poses.csv": b"t,x,y,yaw\n"}
    archive = tmp_path / "scans.zip"
    archive.write_bytes(_zip(members))
    paths = extract_scan_archive(archive, tmp_path / "out", 100, 1 << 30)
    assert [p.name for p in paths] == [f"{t}.png" for t in TIMES]


def test_an_archive_named_in_nanoseconds_is_told_so_without_folder_advice() -> None:
    """Names 1000x the scans' own times read as nanoseconds; an archive has no layout to read it in (QA, session 25)."""
    from service.core.archive import scan_name_time_message

    t_us = 1_600_000_000_000_000
    msg = scan_name_time_message(f"{t_us * 1000}.png", t_us)
    assert msg is not None and msg.startswith(f"scan archive member {t_us * 1000}.png: ")
    assert "the names look like nanoseconds" in msg and "an archive's scans are named <timestamp_us>.png" in msg
    assert "folder" not in msg and "MulRan layout" not in msg


def test_names_within_a_sweep_but_off_are_logged(tmp_path, caplog) -> None:
    """A member named 0.1 s after its first azimuth loads (a naming convention, not another instant) with a warning
    in the server log, as a sequence folder does (QA, session 25)."""
    import logging

    from reradar_core.io.scan import RadarScan, encode_navtech_png_bytes
    from service.core.archive import check_scan_times

    paths = []
    for k, t in enumerate((1_600_000_000_000_000, 1_600_000_000_250_000)):
        azimuths = np.linspace(0.0, 2 * np.pi, 400, endpoint=False)
        scan = RadarScan(np.full((400, 64), 0.1, np.float32), azimuths, t + np.arange(400, dtype=np.int64) * 625,
                         0.0438, 0.0)
        p = tmp_path / f"{t + (100_000 if k else 0)}.png"
        p.write_bytes(encode_navtech_png_bytes(scan))
        paths.append(p)
    with caplog.at_level(logging.WARNING, logger="service.core.archive"):
        check_scan_times(paths)
    assert "1 of 2 uploaded scans are named by a time up to +100.0 ms from their first azimuth's time" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="service.core.archive"):
        check_scan_times(paths[:1])
    assert "first azimuth" not in caplog.text
