"""Regression tests for the session-24 QA of the docs against the service: `/readyz` answered 200 with no map it
could serve (finding 3); an archive whose scans carry one scan time under different names was accepted and failed
only after the whole build, naming an internal file (finding 4; a polar .npy archive of more than one scan failed
so every time); `RERADAR_REDIS_URL=unix://...` (finding 8) works end to end and is now documented and checked.
(Finding 2, `reradar localize --follow --time-unit`, is tested in test_client_robustness.py.)"""

from __future__ import annotations

import io
import os
import shutil
import socket
import subprocess
import sys
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import cv2
import h5py
import httpx
import numpy as np
import pytest

from reradar_core.errors import ScanFormatError
from reradar_core.io.scan import encode_navtech_png_bytes
from service.api.routes.health import readyz
from service.client import ReRadarClient
from service.core.archive import check_scan_times, navtech_png_scan_time_us
from service.core.config import Settings
from service.core.errors import BadRequestError
from service.core.registry import MapEntry, MapRegistry
from service.demo import serve_in_thread

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import (  # noqa: E402
    API_KEY,
    FakeExtractor,
    keyframe_poses,
    keyframe_time,
    make_scan,
    register_map_file,
)

AUTH = {"X-API-Key": API_KEY}
HERE = Path(__file__).resolve().parent


def _png(i: int, t_us: int) -> bytes:
    return encode_navtech_png_bytes(make_scan(i, t_us))


def _npy(i: int, t_us: int) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.round(make_scan(i, t_us).power * 255).astype(np.uint8))  # a polar (A, R) array: no time
    return buf.getvalue()


def _upload(members: dict[str, bytes], times_us: list[int]) -> dict[str, tuple[str, bytes]]:
    """An archive of ``members`` and a t,x,y,yaw pose file (seconds) with the fake keyframe poses at
    ``times_us`` (metres, radians)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    poses = keyframe_poses()
    lines = ["t_s,x,y,yaw"] + [f"{t / 1e6:.6f},{float(poses[i, 0])!r},{float(poses[i, 1])!r},{float(poses[i, 2])!r}"
                               for i, t in enumerate(times_us)]
    return {"archive": ("scans.zip", buf.getvalue()), "poses": ("poses.csv", ("\n".join(lines) + "\n").encode())}


@pytest.fixture(scope="module")
def client(server: tuple[str, Path]) -> Iterator[httpx.Client]:
    url, _ = server
    with httpx.Client(base_url=url, timeout=60) as c:
        yield c


def _wait_built(c: httpx.Client, map_id: str, timeout_s: float = 60) -> dict:
    deadline = time.monotonic() + timeout_s
    while (info := c.get(f"/maps/{map_id}").json())["state"] == "building" and time.monotonic() < deadline:
        time.sleep(0.05)
    return info


# ---- finding 3: /readyz with no map that can be served ---------------------------------------------------------

def test_readyz_is_503_while_every_registered_map_failed(tmp_path: Path, fake_map: Path) -> None:
    """A replica whose maps all failed (here: built with other weights) localizes nothing: /readyz says so with
    a reason (GET and HEAD), is ready again once a map can be served, and a replica with no map at all is ready
    (a fresh fleet must take its first upload)."""
    maps_dir = tmp_path / "maps"
    maps_dir.mkdir()
    shutil.copyfile(fake_map, maps_dir / "old.h5")
    with h5py.File(maps_dir / "old.h5", "r+") as f:
        f.attrs["weights_sha256"] = "0" * 64
    settings = Settings(maps_dir=maps_dir, load_demo_map=False, api_key=API_KEY)
    with serve_in_thread(settings, FakeExtractor()) as url, httpx.Client(base_url=url, timeout=30) as c:
        assert c.get("/maps/old").json()["state"] == "failed"
        assert c.head("/readyz").status_code == 503
        r = c.get("/readyz")
        assert r.status_code == 503, r.text
        body = r.json()
        assert (body["status"], body["maps_ready"], body["maps_building"], body["maps_total"]) == ("not_ready", 0, 0, 1)
        assert body["model_id"] == "fake-extractor"  # loaded: not ready for another reason than loading
        assert body["reason"] == (
            "no map can be served: the registered map has failed and none is being built (GET /maps gives each "
            "one's error); register a map built with the running model, or DELETE /maps/{id} the failed ones")
        assert c.post("/localize", data={"map_id": "old"}, files={"scan": ("q.png", _png(1, 0))}).status_code == 409
        register_map_file(c, fake_map, "good")
        r = c.get("/readyz")
        assert r.status_code == 200 and r.json()["maps_ready"] == 1 and r.json()["reason"] is None
        assert c.delete("/maps/good", headers=AUTH).status_code == 200
        assert c.get("/readyz").status_code == 503
        assert c.delete("/maps/old", headers=AUTH).status_code == 200
        r = c.get("/readyz")
        assert r.status_code == 200 and r.json()["maps_total"] == 0 and r.json()["status"] == "ready"


def test_readyz_counts_a_map_being_built_as_one_to_come(tmp_path: Path) -> None:
    registry = MapRegistry(Settings(maps_dir=tmp_path / "maps", load_demo_map=False, api_key=API_KEY),
                           FakeExtractor())
    request = SimpleNamespace(app=SimpleNamespace(state=SimpleNamespace(reradar=SimpleNamespace(
        registry=registry, extractor=FakeExtractor()))))
    try:
        for i in range(2):
            registry._entries[f"f{i}"] = MapEntry(f"f{i}", registry.path_for(f"f{i}"), "failed", error="bad")
        answer = readyz(request)  # type: ignore[arg-type]
        assert answer.status_code == 503  # type: ignore[union-attr]
        assert b"all 2 registered maps have failed" in answer.body  # type: ignore[union-attr]
        registry._entries["b"] = MapEntry("b", registry.path_for("b"), "building", scans_total=4)
        answer = readyz(request)  # type: ignore[arg-type]
        assert (answer.status, answer.maps_building, answer.maps_total) == ("ready", 1, 3)  # type: ignore[union-attr]
    finally:
        registry.close()


def test_wait_ready_names_the_reason_it_waited_for() -> None:
    body = {"status": "not_ready", "model_id": "m", "maps_total": 1, "reason": "no map can be served: x"}
    transport = httpx.MockTransport(lambda r: httpx.Response(503, json=body))
    with ReRadarClient("http://x", transport=transport) as rc:
        assert rc.ready().reason == "no map can be served: x"
        with pytest.raises(TimeoutError, match=r"last answer: HTTP 503 not_ready \(no map can be served: x\)\)$"):
            rc.wait_ready(timeout_s=0.05, poll_s=0.01)


# ---- finding 4: two scans of one scan time in an archive ----------------------------------------------------

def test_archive_whose_copies_carry_the_originals_scan_time_is_400_before_the_build(
        client: httpx.Client, server: tuple[str, Path]) -> None:
    """QA: a copy of a scan under another name (100 s later) kept the original's embedded time, by which the map
    keys its keyframes; the archive was accepted (202), built whole, then failed naming `<id>.h5` and
    `/timestamps_us`. Now 400 before the 202, naming both archive members and the time."""
    times = [keyframe_time(i) for i in range(4)]
    members = {f"{t}.png": _png(i, t) for i, t in enumerate(times)}
    members[f"{times[1] + 100_000_000}.png"] = members[f"{times[1]}.png"]  # the pixels (and metadata) unchanged
    r = client.post("/maps", data={"map_id": "twice", "preset": "boreas"}, headers=AUTH,
                    files=_upload(members, [*times, times[1] + 100_000_000]))
    assert r.status_code == 400, r.text
    assert r.json()["detail"] == (
        f"scan archive members '{times[1]}.png' and '{times[1] + 100_000_000}.png' carry the same scan time, "
        f"{times[1]} us (the first azimuth timestamp in their Navtech metadata, columns 0-7); a map keeps one "
        "keyframe per scan time, so each scan must be its own sweep: remove the copy, or give it its own time")
    assert client.get("/maps/twice").status_code == 404
    maps_dir = server[1]
    assert not (maps_dir / ".jobs" / "twice.json").exists()
    assert not list((maps_dir / ".staging").glob("job-*"))


def test_polar_npy_archive_builds_keyframes_timed_by_their_names(client: httpx.Client,
                                                                 server: tuple[str, Path]) -> None:
    """A polar .npy carries no time: every keyframe of an .npy archive was at time 0 and the build always failed
    after describing every scan. Its keyframes now carry their file names' times."""
    times = [keyframe_time(i) for i in range(4)]
    r = client.post("/maps", data={"map_id": "polar", "preset": "boreas"}, headers=AUTH,
                    files=_upload({f"{t}.npy": _npy(i, t) for i, t in enumerate(times)}, times))
    assert r.status_code == 202, r.text
    info = _wait_built(client, "polar")
    assert info["state"] == "ready" and info["num_keyframes"] == 4, info
    with h5py.File(server[1] / "polar.h5", "r") as f:
        assert f["timestamps_us"][()].tolist() == times
    hit = client.post("/maps/polar/retrieve", data={"top_k": "1", "preset": "boreas"},
                      files={"scan": ("q.png", _png(2, times[2]))}).json()["keyframes"][0]
    assert (hit["keyframe_id"], hit["timestamp_us"]) == (2, times[2])


def test_a_build_stops_at_the_first_scan_whose_time_an_earlier_scan_had(tmp_path: Path) -> None:
    """The build checks every scan too (the upload reads each PNG's first row only, and skips one it cannot read
    so): it fails at the copy, not after describing the whole archive, naming the members, not the map file."""
    settings = Settings(maps_dir=tmp_path / "maps", load_demo_map=False, api_key=API_KEY, build_batch_size=1)
    registry = MapRegistry(settings, FakeExtractor())
    work = tmp_path / "work"
    work.mkdir()
    times = [keyframe_time(i) for i in range(6)]
    paths = [work / f"{t}.png" for t in times]
    for i, p in enumerate(paths):
        p.write_bytes(_png(i, times[0] if i == 2 else times[i]))  # scan 2 carries scan 0's time
    try:
        entry = registry.start_build("dup", paths, keyframe_poses(), "boreas", work, source="test")
        deadline = time.monotonic() + 60
        while entry.state == "building" and time.monotonic() < deadline:
            time.sleep(0.02)
        assert entry.state == "failed" and entry.scans_done == 2  # scans 0 and 1 described, then refused
        assert entry.error is not None and entry.error.startswith(
            f"scan archive members '{times[0]}.png' and '{times[2]}.png' carry the same scan time, {times[0]} us")
        assert ".h5" not in entry.error and "timestamps_us" not in entry.error
    finally:
        registry.close()


# The first-row time reader is the library's (``navtech_png_first_time_us``): tested under every PNG filter in
# tests/io/test_scan_name_times.py.


def test_a_scan_time_that_cannot_be_read_cheaply_is_left_to_the_build(tmp_path: Path) -> None:
    good = _png(1, keyframe_time(1))
    cases = {"16bit": cv2.imencode(".png", np.zeros((4, 24), np.uint16))[1].tobytes(),
             "colour": cv2.imencode(".png", np.zeros((4, 24, 3), np.uint8))[1].tobytes(),
             "cut": good[:60], "junk": b"not a png at all", "empty": b""}
    for name, data in cases.items():
        (tmp_path / f"{name}.png").write_bytes(data)
        assert navtech_png_scan_time_us(tmp_path / f"{name}.png") is None, name
    png = tmp_path / f"{keyframe_time(1)}.png"  # named by the time it carries (else refused: the name is another instant)
    png.write_bytes(good)
    (tmp_path / "2.png").write_bytes(cases["cut"])  # no time read: left to the build
    (tmp_path / "3.npy").write_bytes(b"")  # an .npy is timed by its name
    check_scan_times([png, tmp_path / "2.png", tmp_path / "3.npy"])
    (tmp_path / f"{keyframe_time(1)}.npy").write_bytes(b"")
    with pytest.raises(BadRequestError, match=r"a polar \.npy's from its file name"):
        check_scan_times([png, tmp_path / f"{keyframe_time(1)}.npy"])


def test_the_build_loader_refuses_the_second_of_two_scan_times(tmp_path: Path) -> None:
    registry = MapRegistry(Settings(maps_dir=tmp_path / "maps", load_demo_map=False, api_key=API_KEY),
                           FakeExtractor())
    try:
        # names within a sweep of the time both carry (further apart, each would be refused for that instead)
        a, b = tmp_path / f"{keyframe_time(0)}.png", tmp_path / f"{keyframe_time(0) + 100_000}.png"
        a.write_bytes(_png(1, keyframe_time(0)))
        b.write_bytes(_png(2, keyframe_time(0)))
        load = registry.build_scan_loader([a, b], "boreas")
        assert load(0).timestamp_us == keyframe_time(0)
        with pytest.raises(ScanFormatError, match=rf"^scan archive members '{a.name}' and '{b.name}' carry the same"):
            load(1)
    finally:
        registry.close()


# ---- finding 8: RERADAR_REDIS_URL=unix://... ------------------------------------------------------------------

@pytest.mark.parametrize(("url", "message"), [
    ("unix://tmp/redis.sock", "after three slashes, e.g. unix:///run/redis/redis.sock; 'tmp' before the path"),
    ("unix://:secret@host/redis.sock", "'host' before the path would be ignored"),
    ("unix://", "names no socket file"),
    ("http://h:6379", r"one of the following schemes \(redis://, rediss://, unix://\)"),
])
def test_redis_urls_redis_would_misread_are_refused(tmp_path: Path, url: str, message: str) -> None:
    from pydantic import ValidationError

    from service.cli import describe_settings_error

    with pytest.raises(ValidationError, match=message) as err:
        Settings(maps_dir=tmp_path, redis_url=url)
    assert "secret" not in describe_settings_error(err.value)  # what `reradar serve` prints (exit 2)


def test_unix_socket_urls_are_read_alike_by_both_clients(tmp_path: Path) -> None:
    from service.core.shared_state import arq_redis_settings, connect

    url = "unix://:p%40ss@/run/redis/redis.sock?db=2"
    assert Settings(maps_dir=tmp_path, redis_url=url).redis_url == url
    rs = arq_redis_settings(url)
    assert (rs.unix_socket_path, rs.database, rs.password) == ("/run/redis/redis.sock", 2, "p@ss")
    kw = connect(url).connection_pool.connection_kwargs
    assert (kw["path"], kw["db"], kw["password"]) == ("/run/redis/redis.sock", 2, "p@ss")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_a_fleet_on_a_redis_unix_socket(tmp_path: Path, fake_map: Path) -> None:
    """An API replica and a build worker on a Redis reached through a Unix socket only (no TCP port): a scan
    uploaded once localizes by scan_id (features in Redis) and a queued archive build is built by the worker."""
    server = shutil.which("redis-server")
    if server is None:
        pytest.skip("redis-server is not installed (the fleet tests install it: apt-get install redis-server)")
    sock = tmp_path / "redis.sock"
    maps_dir = tmp_path / "maps"
    maps_dir.mkdir()
    redis_log = (tmp_path / "redis.log").open("wb")
    procs = [subprocess.Popen([server, "--port", "0", "--unixsocket", str(sock), "--unixsocketperm", "700",
                               "--save", "", "--appendonly", "no", "--dir", str(tmp_path)],
                              stdout=redis_log, stderr=subprocess.STDOUT)]
    env = {**os.environ, "RERADAR_MAPS_DIR": str(maps_dir), "RERADAR_REDIS_URL": f"unix://{sock}?db=0",
           "RERADAR_REDIS_NAMESPACE": "unixtest", "RERADAR_LOAD_DEMO_MAP": "false", "RERADAR_API_KEY": API_KEY,
           "OPENBLAS_NUM_THREADS": "1", "PYTHONPATH": str(HERE.parents[1])}
    port = _free_port()
    logs = {name: tmp_path / f"{name}.log" for name in ("api", "worker")}
    try:
        deadline = time.monotonic() + 20
        while not sock.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        for name, args in (("api", ["api", str(port)]), ("worker", ["worker"])):
            procs.append(subprocess.Popen([sys.executable, str(HERE / "ops_replica.py"), *args], env=env,
                                          cwd=HERE.parents[1], stdout=logs[name].open("wb"), stderr=subprocess.STDOUT))
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30) as c:
            deadline = time.monotonic() + 120
            while True:
                try:
                    if c.get("/readyz").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                assert time.monotonic() < deadline, logs["api"].read_text()[-3000:]
                time.sleep(0.2)
            register_map_file(c, fake_map, "city")
            up = c.post("/scans", files={"scan": ("q.png", _png(2, keyframe_time(2)))})
            assert up.status_code == 201, up.text
            res = c.post("/localize", json={"map_id": "city", "scan_id": up.json()["scan_id"]}).json()
            assert res["status"] == "localized" and res["keyframe"]["keyframe_id"] == 2
            times = [keyframe_time(i) for i in range(4)]
            r = c.post("/maps", data={"map_id": "built"}, headers=AUTH,
                       files=_upload({f"{t}.png": _png(10 + i, t) for i, t in enumerate(times)}, times))
            assert r.status_code == 202, r.text
            info = _wait_built(c, "built", timeout_s=120)
            assert info["state"] == "ready" and info["num_keyframes"] == 4, (info, logs["worker"].read_text()[-3000:])
    finally:
        for proc in reversed(procs):
            proc.terminate()
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)
        redis_log.close()


def test_an_archive_of_3360_bin_scans_without_a_preset_is_refused(client: httpx.Client) -> None:
    """QA (session 24): an archive of boreas-2021 scans (0.04381 m/bin) uploaded without `preset` was read as boreas
    (0.0596 m/bin, the same 3,360 bins) and answered 1.5 m off at confidence 1. A PNG does not say its bin size."""
    times = [keyframe_time(i) for i in range(3)]
    r = client.post("/maps", data={"map_id": "nopreset"}, headers=AUTH,
                    files=_upload({f"{t}.png": _png(i, t) for i, t in enumerate(times)}, times))
    assert r.status_code == 422, r.text
    assert "3360 range bins" in r.json()["detail"] and "give 'preset'" in r.json()["detail"]
    assert client.get("/maps/nopreset").status_code == 404
