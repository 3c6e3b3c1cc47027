"""``reradar serve --workers 2``: a real server (two uvicorn worker processes, the shipped model and demo map)
with a real ``redis-server``. Both workers answer, and answer alike: the same scan gets the same pose from
either, a scan uploaded to one localizes by ``scan_id`` on the other, and a tracking session continues
whichever worker gets its next scan. Without Redis, ``--workers 2`` is refused with what to do instead.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest
from typer.testing import CliRunner

from maps.paths import DEMO_QUERIES_DIR

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_ops_fleet import _free_port, _redis_server  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
_SERVER: dict[str, object] = {}  # the running server's process and folder, for tests that inspect them


def test_workers_without_redis_are_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from reradar_cli.main import app

    monkeypatch.delenv("RERADAR_REDIS_URL", raising=False)
    res = CliRunner().invoke(app, ["serve", "--workers", "2", "--maps-dir", str(tmp_path)])
    assert res.exit_code == 2
    assert "RERADAR_REDIS_URL" in res.output and "--workers 2" in res.output


@pytest.fixture(scope="module")
def two_workers(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    root = tmp_path_factory.mktemp("workers")
    rport, port = _free_port(), _free_port()
    redis_proc = subprocess.Popen([_redis_server(), "--port", str(rport), "--bind", "127.0.0.1", "--save", "",
                                   "--appendonly", "no", "--dir", str(root)], stdout=subprocess.DEVNULL)
    env = {**os.environ, "RERADAR_MAPS_DIR": str(root / "maps"), "RERADAR_REDIS_URL": f"redis://127.0.0.1:{rport}/0",
           "RERADAR_REDIS_NAMESPACE": "workerstest", "RERADAR_LOAD_DEMO_MAP": "true", "RERADAR_LOG_FORMAT": "text",
           "PYTHONPATH": str(REPO)}
    log = (root / "serve.log").open("wb")
    proc = subprocess.Popen([sys.executable, "-m", "reradar_cli", "serve", "--port", str(port), "--workers", "2",
                             "--log-level", "warning"], cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    _SERVER.update(proc=proc, root=root)
    try:
        deadline = time.monotonic() + 300
        while True:
            try:
                if httpx.get(url + "/readyz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail("reradar serve --workers 2 did not start:\n"
                            + (root / "serve.log").read_text(errors="replace")[-3000:])
            time.sleep(0.5)
        yield url
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
        redis_proc.terminate()
        redis_proc.wait(timeout=10)


def _scan(i: int) -> tuple[str, bytes]:
    files = sorted(DEMO_QUERIES_DIR.glob("*.png"))
    return files[i].name, files[i].read_bytes()


def _localize(url: str, data: dict[str, str], scan: tuple[str, bytes]) -> dict:
    # a new connection per request, so the kernel hands requests to either worker
    r = httpx.post(url + "/localize", data=data, files={"scan": (scan[0], scan[1], "image/png")}, timeout=120)
    assert r.status_code == 200, r.text
    return r.json()


def test_both_workers_answer_alike(two_workers: str) -> None:
    scans = [_scan(0), _scan(1)]
    with ThreadPoolExecutor(4) as pool:
        answers = list(pool.map(lambda i: (i % 2, _localize(two_workers, {"map_id": "demo"}, scans[i % 2])),
                                range(16)))
    for q in (0, 1):
        mine = [a for k, a in answers if k == q]
        keys = {(a["status"], a["num_inliers"], a["keyframe"]["keyframe_id"] if a["keyframe"] else None,
                 None if a["pose"] is None else tuple(round(a["pose"][k], 9) for k in ("x_m", "y_m", "yaw_deg")))
                for a in mine}
        assert len(keys) == 1, f"query {q}: the workers disagree: {keys}"
    # /readyz answers as soon as one worker is up; on a busy machine the second may still be loading the model,
    # so keep sending (new connections, same scan, same answer required) until both have served or time is up
    seen = set(keys)
    deadline = time.monotonic() + 180
    while True:
        recent = httpx.get(two_workers + "/ui/api/maps/demo/localizations", params={"limit": 200}, timeout=30)
        replicas = {item["replica"] for item in recent.json()["data"]}
        if len(replicas) >= 2 or time.monotonic() > deadline:
            break
        with ThreadPoolExecutor(4) as pool:
            more = list(pool.map(lambda _: _localize(two_workers, {"map_id": "demo"}, scans[1]), range(4)))
        seen |= {(a["status"], a["num_inliers"], a["keyframe"]["keyframe_id"] if a["keyframe"] else None,
                  None if a["pose"] is None else tuple(round(a["pose"][k], 9) for k in ("x_m", "y_m", "yaw_deg")))
                 for a in more}
        assert len(seen) == 1, f"the workers disagree: {seen}"
    assert len(replicas) == 2, f"expected both workers to serve requests, saw {replicas}"


def test_scan_id_and_tracking_session_across_workers(two_workers: str) -> None:
    name, data = _scan(2)
    up = httpx.post(two_workers + "/scans", files={"scan": (name, data, "image/png")}, timeout=120)
    assert up.status_code == 201, up.text
    scan_id = up.json()["scan_id"]
    by_ref = [httpx.post(two_workers + "/localize", json={"map_id": "demo", "scan_id": scan_id}, timeout=120)
              for _ in range(6)]
    assert all(r.status_code == 200 for r in by_ref), [r.text for r in by_ref]
    assert len({(r.json()["status"], r.json()["num_inliers"]) for r in by_ref}) == 1

    # a session: the first localized answer is global, every later scan (standing still) is tracked from
    # the pose kept in Redis, whichever worker gets it
    for i in range(len(list(DEMO_QUERIES_DIR.glob("*.png")))):
        session = {"map_id": "demo", "session_id": f"vehicle-{i}", "odom_dx_m": "0", "odom_dy_m": "0",
                   "odom_dyaw_deg": "0"}
        first = _localize(two_workers, session, _scan(i))
        if first["status"] == "localized":
            break
    else:
        pytest.fail("no demo query is localized")
    assert first["mode"] == "global"
    later = [_localize(two_workers, session, _scan(i)) for _ in range(6)]
    assert [a["mode"] for a in later] == ["tracking"] * 6


def _descendants(pid: int) -> list[int]:
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                kids = [int(k) for k in (task / "children").read_text().split()]
            except OSError:
                continue
            out += kids
            todo += kids
    return out


def test_workers_share_one_memory_mapped_map_arrays_file(two_workers: str) -> None:
    """Both worker processes serve the demo map's keyframes from the same mapped file (one inode)."""
    proc, root = _SERVER["proc"], _SERVER["root"]
    assert isinstance(proc, subprocess.Popen) and isinstance(root, Path)
    files = sorted((root / "maps" / ".arrays").glob("*.rrarr"))
    assert len(files) == 1, files
    ino = files[0].stat().st_ino
    deadline = time.monotonic() + 180
    while True:  # the second worker may still be loading on a busy machine
        mappers = []
        for pid in _descendants(proc.pid):
            try:
                lines = Path(f"/proc/{pid}/maps").read_text().splitlines()
            except OSError:
                continue
            inodes = {int(line.split()[4]) for line in lines if line.endswith(".rrarr")}
            if inodes:
                assert inodes == {ino}, f"worker {pid} maps another arrays file"
                mappers.append(pid)
        if len(mappers) >= 2 or time.monotonic() > deadline:
            break
        time.sleep(1)
    assert len(mappers) == 2, f"expected both workers to map {files[0].name}, saw {mappers}"
