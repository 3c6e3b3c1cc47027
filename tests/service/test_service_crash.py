"""Crash consistency: the server process is killed with SIGKILL during map installs and builds, restarted on the
same maps folder, and must have lost nothing it accepted (an accepted build is ``failed`` with the reason or
``ready``, never unknown) and left nothing half-written (no partial map under a map's name, no temporary or
staging files)."""

from __future__ import annotations

import io
import json
import random
import sys
import threading
import time
import zipfile
from pathlib import Path

import httpx
import pytest

from maps.store import MapWriter, read_metadata, remove_stale_temp_files
from reradar_core.io.poses import PoseSequence, write_txyyaw_csv
from reradar_core.io.scan import encode_navtech_png_bytes

sys.path.insert(0, str(Path(__file__).resolve().parent))
from attacks import ServerProcess, normal_png  # noqa: E402
from service_test_fakes import API_KEY, N_KEYFRAMES, keyframe_poses, keyframe_time, make_scan  # noqa: E402

AUTH = {"X-API-Key": API_KEY}
SEED = 13


def _archive(tmp_path: Path, n: int = N_KEYFRAMES) -> dict[str, tuple[str, bytes]]:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for i in range(n):
            zf.writestr(f"{keyframe_time(i)}.png", encode_navtech_png_bytes(make_scan(i, keyframe_time(i))))
    poses = keyframe_poses()[:n]
    pose_file = write_txyyaw_csv(PoseSequence([keyframe_time(i) for i in range(n)], poses[:, :2], poses[:, 2]),
                                 tmp_path / "poses.csv")
    return {"archive": ("scans.zip", buf.getvalue()), "poses": ("poses.csv", pose_file.read_bytes())}


def _assert_clean(maps_dir: Path) -> None:
    """No temporary map files, no staging leftovers, every map file complete."""
    assert not list(maps_dir.glob(".*.tmp")), list(maps_dir.glob(".*.tmp"))
    staging = maps_dir / ".staging"
    assert not staging.exists() or not any(staging.iterdir()), list(staging.iterdir())
    for path in maps_dir.glob("*.h5"):
        assert read_metadata(path).num_keyframes >= 1


def test_build_killed_midway_is_failed_after_restart(tmp_path: Path) -> None:
    maps_dir = tmp_path / "maps"
    maps_dir.mkdir()
    files = _archive(tmp_path)
    server = ServerProcess(maps_dir, describe_delay_s=0.3).start()
    try:
        r = httpx.post(f"{server.url}/maps", data={"map_id": "built", "preset": "boreas"}, files=files, headers=AUTH, timeout=60)
        assert r.status_code == 202, r.text
        record = json.loads((maps_dir / ".jobs" / "built.json").read_text())
        assert record["state"] == "building" and record["scans_total"] == N_KEYFRAMES
        time.sleep(0.3)  # describing the 6 scans takes >= 1.8 s
        assert httpx.get(f"{server.url}/maps/built").json()["state"] == "building"
        server.kill9()
    finally:
        server.stop()
    assert not (maps_dir / "built.h5").exists()
    with ServerProcess(maps_dir) as server, httpx.Client(base_url=server.url, timeout=60) as c:
        info = c.get("/maps/built").json()
        assert info["state"] == "failed" and "stopped" in info["error"] and info["scans_total"] == N_KEYFRAMES
        assert c.post("/localize", data={"map_id": "built"}, files={"scan": ("q.png", normal_png())}).status_code == 409
        _assert_clean(maps_dir)
        assert c.post("/maps", data={"map_id": "built", "preset": "boreas"}, files=files,
                      headers=AUTH).status_code == 409
        assert c.delete("/maps/built", headers=AUTH).status_code == 200
        assert not (maps_dir / ".jobs" / "built.json").exists()
        assert c.post("/maps", data={"map_id": "built", "preset": "boreas"}, files=files,
                      headers=AUTH).status_code == 202
        deadline = time.monotonic() + 60
        while (info := c.get("/maps/built").json())["state"] == "building" and time.monotonic() < deadline:
            time.sleep(0.1)
        assert info["state"] == "ready" and info["num_keyframes"] == N_KEYFRAMES
        assert not (maps_dir / ".jobs" / "built.json").exists()  # done: the map file is the record


def test_kill9_at_random_moments_of_install_and_build(tmp_path: Path, fake_map: Path) -> None:
    maps_dir = tmp_path / "maps"
    maps_dir.mkdir()
    archive = _archive(tmp_path)
    rng = random.Random(SEED)
    server = ServerProcess(maps_dir, describe_delay_s=0.02).start()
    try:
        accepted_builds: set[str] = set()
        for trial in range(4):
            upload_id, build_id = f"up{trial}", f"bd{trial}"
            answers: dict[str, int] = {}

            def send(map_id: str, files: dict, answers: dict[str, int] = answers, url: str = server.url) -> None:
                try:
                    r = httpx.post(f"{url}/maps", data={"map_id": map_id}, files=files, headers=AUTH, timeout=30)
                    answers[map_id] = r.status_code
                except httpx.TransportError:
                    answers[map_id] = -1

            threads = [threading.Thread(target=send, args=(upload_id, {"map_file": ("m.h5", fake_map.read_bytes())})),
                       threading.Thread(target=send, args=(build_id, archive))]
            for t in threads:
                t.start()
            time.sleep(rng.uniform(0.0, 0.25))
            server.kill9()
            for t in threads:
                t.join(timeout=30)
            if answers.get(build_id) == 202:
                accepted_builds.add(build_id)
            server = ServerProcess(maps_dir, describe_delay_s=0.02).start()
            with httpx.Client(base_url=server.url, timeout=30) as c:
                up = c.get(f"/maps/{upload_id}")
                if answers.get(upload_id) == 201:
                    assert up.status_code == 200 and up.json()["state"] == "ready"
                if up.status_code == 200:
                    assert up.json()["num_keyframes"] == N_KEYFRAMES
                else:
                    assert up.status_code == 404 and not (maps_dir / f"{upload_id}.h5").exists()
                for bid in accepted_builds:
                    info = c.get(f"/maps/{bid}")
                    assert info.status_code == 200, (bid, info.text)  # never unknown once accepted
                    assert info.json()["state"] in ("failed", "ready")  # a restart never resumes a build
                bd = c.get(f"/maps/{build_id}")
                assert bd.status_code in (200, 404)
                if bd.status_code == 200 and bd.json()["state"] == "failed":
                    assert "stopped" in bd.json()["error"]
            _assert_clean(maps_dir)
    finally:
        server.stop()


def test_writers_of_dead_processes_leave_no_temp_files(tmp_path: Path) -> None:
    from maps.store import MapMetadata

    dead = tmp_path / ".route.h5.999999999.1.tmp"  # pid beyond pid_max: never alive
    dead.write_bytes(b"partial")
    mine = tmp_path / f".other.h5.{__import__('os').getpid()}.1.tmp"
    mine.write_bytes(b"in progress")
    assert remove_stale_temp_files(tmp_path) == [dead]
    assert mine.exists()
    dead.write_bytes(b"partial")
    meta = MapMetadata(model_id="m", weights_sha256="0" * 64, radar_preset="boreas", cartesian_width_px=8,
                       cartesian_resolution_m=1.0, descriptor_dim=4, local_descriptor_dim=2)
    with pytest.raises(RuntimeError):
        with MapWriter(tmp_path / "x.h5", meta):  # every writer (the CLI's build-map too) cleans up first
            assert not dead.exists()
            raise RuntimeError("abort")
    assert not (tmp_path / "x.h5").exists() and not list(tmp_path.glob(".x.h5.*.tmp"))
