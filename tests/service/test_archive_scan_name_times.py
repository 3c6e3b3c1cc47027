"""A map built from an uploaded scan archive takes each keyframe's pose from the poses file at the time its member's
name gives (``<timestamp_us>.png``), and keys the keyframe by the time the PNG carries (its first azimuth's,
columns 0-7). A member whose name and embedded time lay more than one sweep apart was accepted (202) and built
into a map whose keyframe had the pose of one instant and the time of another. It is now refused like a sequence
folder's (``load_sequence``, the library's ``scan_name_time_mismatch``): a 400 before the 202, naming the member by
its name in the archive, both times and what to do; a PNG whose first row cannot be read cheaply is decoded for it.
"""

from __future__ import annotations

import io
import sys
import time
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient
from pydantic import SecretStr

from reradar_core.errors import ScanFormatError
from reradar_core.io.datasets import scan_name_time_mismatch
from reradar_core.io.presets import get_preset
from reradar_core.io.scan import encode_navtech_png_bytes, navtech_png_first_time_us
from service.core.archive import check_scan_times, navtech_png_scan_time_us, scan_name_time_message
from service.core.config import Settings
from service.core.errors import BadRequestError
from service.core.registry import MapRegistry
from service.main import create_app

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import API_KEY, FakeExtractor, keyframe_poses, keyframe_time, make_scan  # noqa: E402

AUTH = {"X-API-Key": API_KEY}
N = 4
TIMES = [keyframe_time(i) for i in range(N)]  # 0.25 s apart: one sweep
LATER_US = 3_000_000  # a member carrying the time of a scan 3 s after its name's: another instant


def _png(i: int, t_us: int) -> bytes:
    return encode_navtech_png_bytes(make_scan(i, t_us))


def _with_chunks_before_image(png: bytes, n: int = 300) -> bytes:
    """``png`` with ``n`` tEXt chunks after its header: too many for the cheap first-row read (it gives up after
    256), which the build's decoder (OpenCV) reads as the same image."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return len(body).to_bytes(4, "big") + kind + body + zlib.crc32(kind + body).to_bytes(4, "big")

    head = 8 + 25  # signature, IHDR (length, type, 13 bytes, CRC)
    return png[:head] + b"".join(chunk(b"tEXt", b"Comment\x00%d" % i) for i in range(n)) + png[head:]


def _files(members: dict[str, bytes]) -> dict[str, tuple[str, bytes]]:
    """A zip of ``members`` and a t,x,y,yaw pose file (seconds) with the fake keyframe poses at ``TIMES``."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    poses = keyframe_poses()
    rows = [f"{t / 1e6:.6f},{float(poses[i, 0])!r},{float(poses[i, 1])!r},{float(poses[i, 2])!r}"
            for i, t in enumerate(TIMES)]
    return {"archive": ("scans.zip", buf.getvalue()),
            "poses": ("poses.csv", ("\n".join(["t_s,x,y,yaw", *rows]) + "\n").encode())}


def _members(carried: dict[int, int] | None = None) -> dict[str, bytes]:
    """Member ``i`` named ``TIMES[i]``.png, carrying ``carried[i]`` (default: its name's time)."""
    carried = carried or {}
    return {f"{t}.png": _png(i, carried.get(i, t)) for i, t in enumerate(TIMES)}


@contextmanager
def _client(maps_dir: Path, **settings: Any) -> Iterator[TestClient]:
    cfg = Settings(maps_dir=maps_dir, load_demo_map=False, api_key=SecretStr(API_KEY), torch_threads=1, **settings)
    with TestClient(create_app(cfg, FakeExtractor())) as client:
        yield client


def _post(client: TestClient, map_id: str, members: dict[str, bytes]) -> Any:
    return client.post("/maps", data={"map_id": map_id, "preset": "boreas"}, files=_files(members), headers=AUTH)


def _wait_built(client: TestClient, map_id: str, timeout_s: float = 60) -> dict:
    deadline = time.monotonic() + timeout_s
    while (info := client.get(f"/maps/{map_id}").json())["state"] == "building" and time.monotonic() < deadline:
        time.sleep(0.05)
    return info


def _nothing_kept(client: TestClient, maps_dir: Path, map_id: str) -> None:
    assert client.get(f"/maps/{map_id}").status_code == 404
    assert not (maps_dir / ".jobs" / f"{map_id}.json").exists() and not (maps_dir / f"{map_id}.h5").exists()
    assert not list((maps_dir / ".staging").glob("job-*"))


def test_a_member_carrying_another_instant_than_its_name_is_400_before_the_build(tmp_path: Path) -> None:
    maps_dir = tmp_path / "maps"
    name = f"{TIMES[2]}.png"
    carried = TIMES[2] + LATER_US
    with _client(maps_dir) as client:
        r = _post(client, "renamed", _members({2: carried}))
        assert r.status_code == 400, r.text
        detail = r.json()["detail"]
        # the library's rule and words (a sequence folder's), said of the archive member
        library = scan_name_time_mismatch(name, TIMES[2], carried, get_preset("boreas"))
        assert library is not None
        assert detail == "scan archive member " + library.removeprefix("scan ").replace("folder", "archive")
        assert detail.startswith(f"scan archive member {name}: its file name gives the time {TIMES[2]} us, but the "
                                 f"timestamps in the scan (columns 0-7, first azimuth) say {carried} us, 3 s later")
        assert f"rename it to {carried}.png" in detail and "remove it from the archive" in detail
        assert str(tmp_path) not in detail and ".staging" not in detail and "job-" not in detail
        _nothing_kept(client, maps_dir, "renamed")
        # several: the first is named, and how many disagree is said
        r = _post(client, "renamed", _members({1: TIMES[1] - LATER_US, 3: TIMES[3] + LATER_US}))
        assert r.status_code == 400, r.text
        assert r.json()["detail"].startswith(f"scan archive member {TIMES[1]}.png: ")
        assert r.json()["detail"].endswith(f"(2 of {N} scans disagree so; the first is named)")
        _nothing_kept(client, maps_dir, "renamed")
        # each member named by the time it carries, the archive builds under that id
        r = _post(client, "renamed", _members())
        assert r.status_code == 202, r.text
        assert _wait_built(client, "renamed")["state"] == "ready"


def test_a_name_within_one_sweep_of_the_embedded_time_builds(tmp_path: Path) -> None:
    """Any azimuth of the sweep is within one period of the first: a name 100 ms off is a naming convention, not
    another instant (the library's tolerance)."""
    with _client(tmp_path / "maps") as client:
        r = _post(client, "near", _members({2: TIMES[2] - 100_000}))
        assert r.status_code == 202, r.text
        info = _wait_built(client, "near")
        assert info["state"] == "ready" and info["num_keyframes"] == N, info
        # the preset's name in any case is stored as the preset's own (QA session 40: "BOREAS" was stored so)
        r = client.post("/maps", data={"map_id": "upper", "preset": "BOREAS"}, files=_files(_members()), headers=AUTH)
        assert r.status_code == 202, r.text
        info = _wait_built(client, "upper")
        assert info["state"] == "ready" and info["radar_preset"] == "boreas", info


def test_a_service_build_stores_the_place_repetition_under_the_services_settings(tmp_path: Path) -> None:
    """QA (session 28): the in-process build measured it under the default settings, which a service configured
    otherwise then ignored (each keyframe measured again as it first won)."""
    from maps.store import open_map
    from reradar_core.localization import LocalizationConfig, repetition_settings

    own = LocalizationConfig(place_margin_radius_m=25.0)
    with _client(tmp_path / "maps", localization=own) as client:
        assert _post(client, "own", _members()).status_code == 202
        assert _wait_built(client, "own")["place_repetition"] == "stored"
    with open_map(tmp_path / "maps" / "own.h5") as m:
        assert m.place_repetition is not None and m.place_repetition.settings == repetition_settings(own)


def test_a_copy_under_another_name_is_still_called_a_copy(tmp_path: Path) -> None:
    """A copy carries the original's time: its name disagrees with it too, but what it is (a second scan of one
    time) is what is said."""
    members = _members()
    members[f"{TIMES[3] + 100_000_000}.png"] = members[f"{TIMES[1]}.png"]
    with _client(tmp_path / "maps") as client:
        r = _post(client, "copy", members)
        assert r.status_code == 400, r.text
        assert r.json()["detail"].startswith(f"scan archive members '{TIMES[1]}.png' and "
                                             f"'{TIMES[3] + 100_000_000}.png' carry the same scan time")


def test_an_image_that_is_no_navtech_scan_is_left_to_the_decoder(tmp_path: Path) -> None:
    """An image without Navtech metadata whose first pixels happen to read as a time is not reported as a name
    mismatch (the one disagreement is decoded first, as the build would): the decoder says what it is."""
    foreign = np.random.default_rng(0).integers(0, 256, size=(400, 3371), dtype=np.uint8)
    foreign[0, :8] = [10, 20, 30, 40, 50, 60, 5, 0]  # a positive int64 below 2^62: not its name's time
    data = cv2.imencode(".png", foreign)[1].tobytes()
    path = tmp_path / f"{TIMES[0]}.png"
    path.write_bytes(data)
    assert navtech_png_first_time_us(path) == int(foreign[0, :8].view("<i8")[0])
    members = _members()
    members[f"{TIMES[0]}.png"] = data
    with _client(tmp_path / "maps") as client:
        r = _post(client, "foreign", members)
        assert r.status_code == 422, r.text  # the first scan is decoded before the 202
        assert "its file name gives" not in r.json()["detail"] and f"{TIMES[0]}.png" in r.json()["detail"]


def test_a_member_the_cheap_read_cannot_time_is_decoded_and_refused_before_the_build(tmp_path: Path) -> None:
    """The upload reads each PNG's first row only; one it cannot read so is decoded as the build would decode it
    and checked alike: a 400 before the 202, naming the member (it was a 202 and a failed build; QA: docs/SERVICE.md
    promises the 400). More in test_archive_unread_first_row.py."""
    data = _with_chunks_before_image(_png(3, TIMES[3] + LATER_US))
    path = tmp_path / f"{TIMES[3]}.png"
    path.write_bytes(data)
    assert navtech_png_first_time_us(path) is None
    members = _members()
    members[f"{TIMES[3]}.png"] = data
    maps_dir = tmp_path / "maps"
    with _client(maps_dir) as client:
        r = _post(client, "late", members)
        assert r.status_code == 400, r.text
        detail = r.json()["detail"]
        assert detail.startswith(f"scan archive member {TIMES[3]}.png: its file name gives the time {TIMES[3]} us"), detail
        assert str(maps_dir) not in detail and ".h5" not in detail
        _nothing_kept(client, maps_dir, "late")


def test_the_build_loader_refuses_a_png_whose_name_is_another_instant(tmp_path: Path) -> None:
    registry = MapRegistry(Settings(maps_dir=tmp_path / "maps", load_demo_map=False, api_key=SecretStr(API_KEY)),
                           FakeExtractor())
    try:
        good, bad, near = (tmp_path / f"{TIMES[0]}.png", tmp_path / f"{TIMES[1]}.png", tmp_path / f"{TIMES[2]}.png")
        good.write_bytes(_png(0, TIMES[0]))
        bad.write_bytes(_png(1, TIMES[1] - LATER_US))
        near.write_bytes(_png(2, TIMES[2] + 200_000))
        load = registry.build_scan_loader([good, bad, near], None)
        assert load(0).timestamp_us == TIMES[0]
        with pytest.raises(ScanFormatError, match=rf"^scan archive member {TIMES[1]}\.png: .* 3 s earlier"):
            load(1)
        assert load(2).timestamp_us == TIMES[2] + 200_000
    finally:
        registry.close()


def test_check_scan_times_rule_and_the_library_reader(tmp_path: Path) -> None:
    """The archive's rule is the library's (one sweep of the preset); .npy members are timed by their names; the
    cheap first-row read is the library's (the service's copy is gone, its name kept)."""
    assert navtech_png_scan_time_us is navtech_png_first_time_us
    sweep_us = int(get_preset("boreas").sweep_period_s * 1e6)
    assert scan_name_time_message(f"{TIMES[0]}.png", TIMES[0] + sweep_us) is None
    assert scan_name_time_message(f"{TIMES[0]}.png", TIMES[0] + sweep_us + 1) is not None
    assert scan_name_time_message(f"{TIMES[0]}.npy", 0) is None
    a, b = tmp_path / f"{TIMES[0]}.png", tmp_path / f"{TIMES[1]}.png"
    a.write_bytes(_png(0, TIMES[0]))
    b.write_bytes(_png(1, TIMES[1] + LATER_US))
    check_scan_times([a])
    with pytest.raises(BadRequestError, match=rf"^scan archive member {TIMES[1]}\.png: "):
        check_scan_times([a, b])
    check_scan_times([a, b], "boreas", lambda path: None)  # the decoder refuses it: left to the build
    decoded: list[Path] = []

    def decode(path: Path) -> int:
        decoded.append(path)
        return TIMES[1] + LATER_US

    with pytest.raises(BadRequestError, match=r"3 s later"):
        check_scan_times([a, b], "boreas", decode)
    assert decoded == [b]  # only the disagreeing scan is decoded
