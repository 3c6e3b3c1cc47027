"""A small fleet on one machine: a real ``redis-server``, two real uvicorn API replicas (separate processes)
sharing one maps folder, and build workers (``reradar worker``'s ``run_worker``), all with the tests' fake
extractor. Shows: a scan uploaded on A localizes by ``scan_id`` on B; a map registered or deleted through A is
served or dropped by B within 2 s; a queued build survives its worker being killed; cancel; Redis down.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np
import pytest

from reradar_core.io.poses import PoseSequence, write_txyyaw_csv
from reradar_core.io.scan import encode_navtech_png_bytes

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import API_KEY, damaged_png, keyframe_time, make_scan, register_map_file  # noqa: E402

AUTH = {"X-API-Key": API_KEY}
HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
NAMESPACE = "opstest"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _redis_server() -> str:
    found = shutil.which("redis-server")
    if found:
        return found
    if os.environ.get("CI"):
        pytest.fail("redis-server missing: .ci/run installs it (apt-get install redis-server)")
    if hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("apt-get"):
        subprocess.run(["apt-get", "install", "-y", "-qq", "--no-install-recommends", "redis-server"],
                       env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"}, capture_output=True, timeout=600,
                       check=False)
        found = shutil.which("redis-server")
        if found:
            return found
    pytest.skip("redis-server is not installed and cannot be installed here (needs root and apt-get)")


def _wait(cond: Callable[[], object], timeout_s: float, what: str, step_s: float = 0.05) -> object:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = cond()
        if value:
            return value
        time.sleep(step_s)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


@dataclass
class Fleet:
    redis_url: str
    redis_proc: subprocess.Popen[bytes]
    maps_dir: Path
    logs: Path
    env: dict[str, str]
    a: httpx.Client
    b: httpx.Client
    pids: dict[str, int] = field(default_factory=dict)
    procs: list[subprocess.Popen[bytes]] = field(default_factory=list)

    def start(self, name: str, *args: str, extra_env: dict[str, str] | None = None) -> subprocess.Popen[bytes]:
        log = (self.logs / f"{name}.log").open("ab")
        proc = subprocess.Popen([sys.executable, str(HERE / "ops_replica.py"), *args], cwd=REPO,
                                env={**self.env, **(extra_env or {})}, stdout=log, stderr=subprocess.STDOUT)
        self.procs.append(proc)
        self.pids[name] = proc.pid
        return proc

    def log(self, name: str) -> str:
        return (self.logs / f"{name}.log").read_text(errors="replace")[-4000:]

    def redis(self):  # type: ignore[no-untyped-def]
        import redis

        return redis.Redis.from_url(self.redis_url)


def _stop(proc: subprocess.Popen[bytes], sig: int = signal.SIGTERM) -> None:
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    root = tmp_path_factory.mktemp("fleet")
    maps_dir, logs = root / "maps", root / "logs"
    maps_dir.mkdir()
    logs.mkdir()
    port = _free_port()
    redis_proc = subprocess.Popen([_redis_server(), "--port", str(port), "--bind", "127.0.0.1", "--save", "",
                                   "--appendonly", "no", "--dir", str(root)],
                                  stdout=(logs / "redis.log").open("wb"), stderr=subprocess.STDOUT)
    redis_url = f"redis://127.0.0.1:{port}/0"
    env = {**os.environ, "RERADAR_MAPS_DIR": str(maps_dir), "RERADAR_REDIS_URL": redis_url,
           "RERADAR_REDIS_NAMESPACE": NAMESPACE, "RERADAR_LOAD_DEMO_MAP": "false", "RERADAR_API_KEY": API_KEY,
           "RERADAR_BUILD_HEARTBEAT_STALE_S": "4", "RERADAR_MAP_SYNC_INTERVAL_S": "60",  # events only "RERADAR_BUILD_BATCH_SIZE": "2", "OPENBLAS_NUM_THREADS": "1",
           "PYTHONPATH": str(REPO)}
    ports = _free_port(), _free_port()
    fl = Fleet(redis_url, redis_proc, maps_dir, logs, env, httpx.Client(base_url=f"http://127.0.0.1:{ports[0]}",
               timeout=30), httpx.Client(base_url=f"http://127.0.0.1:{ports[1]}", timeout=30))
    try:
        _wait(lambda: fl.redis().ping(), 20, "redis-server", step_s=0.1)  # type: ignore[no-untyped-call]
    except Exception:  # noqa: BLE001 - ping raises until the server listens
        pass
    fl.start("api-a", "api", str(ports[0]))
    fl.start("api-b", "api", str(ports[1]))

    def ready(c: httpx.Client) -> bool:
        try:
            return c.get("/readyz").status_code == 200
        except httpx.TransportError:
            return False

    try:
        for name, c in (("api-a", fl.a), ("api-b", fl.b)):
            try:
                _wait(lambda c=c: ready(c), 180, f"{name} ready", step_s=0.2)
            except AssertionError:
                pytest.fail(f"{name} did not start:\n{fl.log(name)}")
        yield fl
    finally:
        for proc in fl.procs:
            _stop(proc)
        _stop(redis_proc)
        fl.a.close()
        fl.b.close()


def _poses(n: int) -> np.ndarray:
    return np.column_stack([np.arange(n) * 25.0, np.zeros(n), np.zeros(n)])


def _archive(n: int, seed0: int = 100, corrupt: int | None = None) -> dict[str, tuple[str, bytes]]:
    """``corrupt``: that scan's data is damaged past its first rows (its time reads at upload, the build refuses it)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for i in range(n):
            scan = make_scan(seed0 + i, keyframe_time(i))
            data = damaged_png(scan) if i == corrupt else encode_navtech_png_bytes(scan)
            zf.writestr(f"{keyframe_time(i)}.png", data)
    poses = _poses(n)
    csv = io.StringIO()
    seq = PoseSequence([keyframe_time(i) for i in range(n)], poses[:, :2], poses[:, 2])
    path = Path(os.environ.get("TMPDIR", "/tmp")) / f"ops-poses-{os.getpid()}-{n}.csv"
    write_txyyaw_csv(seq, path)
    csv.write(path.read_text())
    path.unlink()
    return {"archive": ("scans.zip", buf.getvalue()), "poses": ("poses.csv", csv.getvalue().encode())}


def _png(seed: int, t_us: int) -> bytes:
    return encode_navtech_png_bytes(make_scan(seed, t_us))


def _state(c: httpx.Client, map_id: str) -> str | None:
    r = c.get(f"/maps/{map_id}")
    return r.json()["state"] if r.status_code == 200 else None


def test_map_registered_through_a_is_served_by_b_within_2s(fleet: Fleet, fake_map: Path) -> None:
    assert fleet.b.get("/maps/city").status_code == 404
    register_map_file(fleet.a, fake_map, "city")
    t0 = time.monotonic()
    _wait(lambda: _state(fleet.b, "city") == "ready", 10, "map city on replica B")
    elapsed = time.monotonic() - t0
    assert elapsed < 2.0, f"replica B served the map after {elapsed:.2f} s"
    res = fleet.b.post("/localize", data={"map_id": "city"}, files={"scan": ("q.png", _png(3, keyframe_time(3)))})
    assert res.status_code == 200 and res.json()["status"] == "localized" and res.json()["keyframe"]["keyframe_id"] == 3


def test_scan_uploaded_on_a_localizes_by_scan_id_on_b(fleet: Fleet) -> None:
    up = fleet.a.post("/scans", files={"scan": ("q.png", _png(2, keyframe_time(2)))})
    assert up.status_code == 201, up.text
    scan_id = up.json()["scan_id"]
    res = fleet.b.post("/localize", json={"map_id": "city", "scan_id": scan_id})
    assert res.status_code == 200, res.text
    body = res.json()
    assert body["status"] == "localized" and body["keyframe"]["keyframe_id"] == 2 and body["scan_id"] == scan_id
    hits = fleet.b.post("/maps/city/retrieve", json={"scan_id": scan_id, "top_k": 2}).json()["keyframes"]
    assert hits[0]["keyframe_id"] == 2
    # the features live under the namespaced, versioned key of their uploader (keyless loopback here) with the TTL
    ttl = fleet.redis().pttl(f"{NAMESPACE}:v1:scan:loopback:{scan_id}")
    assert 0 < ttl <= 600_000
    missing = fleet.b.post("/localize", json={"map_id": "city", "scan_id": "0" * 32})
    assert missing.status_code == 404


def test_recent_localizations_are_shared(fleet: Fleet) -> None:
    fixes = fleet.a.get("/ui/api/maps/city/localizations", params={"limit": 10}).json()["data"]
    # the localizations of the tests above were all served by replica B; replica A sees them
    assert len(fixes) >= 2 and all(f["replica"].endswith(f":{fleet.pids['api-b']}") for f in fixes)
    assert fixes[0]["keyframe_id"] == 2 and fixes[0]["status"] == "localized"


def test_map_deleted_through_a_is_dropped_by_b_within_2s(fleet: Fleet, fake_map: Path) -> None:
    with fake_map.open("rb") as fh:
        assert fleet.a.post("/maps", data={"map_id": "temp"}, files={"map_file": ("f.h5", fh)},
                            headers=AUTH).status_code == 201
    _wait(lambda: _state(fleet.b, "temp") == "ready", 5, "map temp on B")
    assert fleet.a.delete("/maps/temp", headers=AUTH).status_code == 200
    t0 = time.monotonic()
    _wait(lambda: fleet.b.get("/maps/temp").status_code == 404, 10, "map temp dropped on B")
    elapsed = time.monotonic() - t0
    assert elapsed < 2.0, f"replica B dropped the map after {elapsed:.2f} s"


def test_queued_build_survives_worker_kill(fleet: Fleet) -> None:
    n = 12
    slow = {"OPS_FAKE_SCAN_DELAY_S": "0.4"}
    w1 = fleet.start("worker-1", "worker", extra_env=slow)
    r = fleet.a.post("/maps", data={"map_id": "built", "preset": "boreas"}, files=_archive(n), headers=AUTH)
    assert r.status_code == 202, r.text
    assert r.json()["state"] == "building" and r.json()["scans_total"] == n
    # every replica shows the build and its progress (from the job record)
    _wait(lambda: (fleet.b.get("/maps/built").json().get("scans_done", 0) >= 2), 60, "build progress on B")
    rec = {k.decode(): v.decode() for k, v in fleet.redis().hgetall(f"{NAMESPACE}:v1:build:built").items()}
    assert rec["state"] == "running" and rec["worker"].endswith(f":{w1.pid}")
    _stop(w1, signal.SIGKILL)
    info = fleet.b.get("/maps/built").json()
    assert info["state"] == "building" and 0 < info["scans_done"] < n
    # with no worker left, the map says what is missing (stale after 4 s here), on every replica
    _wait(lambda: "reradar worker" in (fleet.b.get("/maps/built").json().get("note") or ""), 20, "no-worker note")
    listed = {m["id"]: m for m in fleet.a.get("/maps").json()["data"]}
    assert "reradar worker" in (listed["built"].get("note") or "")
    events = fleet.redis().pubsub(ignore_subscribe_messages=True)
    events.subscribe(f"{NAMESPACE}:v1:maps:events")
    fleet.start("worker-2", "worker", extra_env={"OPS_FAKE_SCAN_DELAY_S": "0.05"})
    try:
        _wait(lambda: _state(fleet.b, "built") == "ready", 90, "the rebuilt map on B", step_s=0.2)
    except AssertionError:
        pytest.fail(f"build not finished after the worker kill:\n{fleet.log('worker-2')}")
    assert fleet.b.get("/maps/built").json()["num_keyframes"] == n
    assert fleet.b.get("/maps/built").json()["note"] is None
    _wait(lambda: _state(fleet.a, "built") == "ready", 5, "the rebuilt map on A")
    ops = []
    deadline = time.monotonic() + 1.0  # everything is buffered already; None also stands for skipped messages
    while time.monotonic() < deadline:
        if (msg := events.get_message(timeout=0.1)) is not None:
            ops.append(json.loads(msg["data"]))
    events.close()
    # the worker announces progress and the finished map (replicas load it on the event, not on a timer)
    built = [o for o in ops if o["op"] == "built" and o["map_id"] == "built"]
    assert len(built) == 1 and built[0]["origin"].endswith(f":{fleet.pids['worker-2']}")
    assert any(o["op"] == "progress" for o in ops)
    rec = {k.decode(): v.decode() for k, v in fleet.redis().hgetall(f"{NAMESPACE}:v1:build:built").items()}
    assert rec["state"] == "ready" and rec["attempts"] == "2" and rec["worker"].endswith(f":{fleet.pids['worker-2']}")
    assert not any((fleet.maps_dir / ".build-queue").iterdir())  # the job's scans are cleaned up
    res = fleet.a.post("/localize", data={"map_id": "built"}, files={"scan": ("q.png", _png(105, keyframe_time(5)))})
    assert res.json()["status"] == "localized" and res.json()["keyframe"]["keyframe_id"] == 5


def test_cancel_a_running_build(fleet: Fleet) -> None:
    slow = fleet.start("worker-3", "worker", extra_env={"OPS_FAKE_SCAN_DELAY_S": "0.5"})
    _stop(next(p for p in fleet.procs if p.pid == fleet.pids["worker-2"]))  # only the slow worker takes it
    r = fleet.a.post("/maps", data={"map_id": "doomed", "preset": "boreas"}, files=_archive(16, seed0=200), headers=AUTH)
    assert r.status_code == 202, r.text
    _wait(lambda: fleet.a.get("/maps/doomed").json().get("scans_done", 0) >= 2, 60, "doomed build running")
    assert fleet.b.delete("/maps/doomed", headers=AUTH).status_code == 200  # cancel through the other replica
    _wait(lambda: fleet.a.get("/maps/doomed").status_code == 404 and fleet.b.get("/maps/doomed").status_code == 404,
          30, "cancelled build gone on both replicas")
    _wait(lambda: not fleet.redis().exists(f"{NAMESPACE}:v1:build:doomed"), 30, "job record removed")
    assert not (fleet.maps_dir / "doomed.h5").exists()
    assert slow.poll() is None  # the worker lives on


def test_worker_health_survives_eviction_of_expiring_keys(fleet: Fleet) -> None:
    """QA (session 20): under ``volatile-ttl`` a full Redis evicted the worker's 11 s health key first, so
    ``reradar worker --check`` reported a live worker dead; its heartbeats now live in a hash without a TTL."""
    import socket

    from service.core.config import Settings
    from service.worker import check_health

    settings = Settings(maps_dir=fleet.maps_dir, redis_url=fleet.redis_url, redis_namespace=NAMESPACE)
    _wait(lambda: check_health(settings), 20, "a worker heartbeat")
    assert fleet.redis().ttl(f"{NAMESPACE}:v1:worker-heartbeats") == -1  # no TTL: never evicted by volatile-ttl
    last = float(fleet.redis().hget(f"{NAMESPACE}:v1:worker-heartbeats", socket.gethostname()))
    assert not check_health(settings, now=last + 30.0)  # a stale heartbeat is a dead worker


def test_cancel_a_queued_build_frees_its_id_at_once(fleet: Fleet) -> None:
    """QA (session 20): a build cancelled while still queued held its id until a worker dequeued it (hours behind
    a long build, forever without a worker): POST said 409 'DELETE first' and DELETE said 404."""
    busy = fleet.a.post("/maps", data={"map_id": "busy", "preset": "boreas"}, files=_archive(16, seed0=400), headers=AUTH)
    assert busy.status_code == 202, busy.text
    _wait(lambda: fleet.a.get("/maps/busy").json().get("scans_done", 0) >= 1, 60, "busy build running")
    r = fleet.a.post("/maps", data={"map_id": "waiting", "preset": "boreas"}, files=_archive(4, seed0=500), headers=AUTH)
    assert r.status_code == 202, r.text  # queued behind "busy" (one build per worker)
    job_id = fleet.redis().hget(f"{NAMESPACE}:v1:build:waiting", "job_id").decode()
    assert fleet.b.delete("/maps/waiting", headers=AUTH).status_code == 200
    assert not fleet.redis().exists(f"{NAMESPACE}:v1:build:waiting")
    assert not (fleet.maps_dir / ".build-queue" / job_id).exists()
    again = fleet.a.post("/maps", data={"map_id": "waiting", "preset": "boreas"}, files=_archive(4, seed0=500), headers=AUTH)
    assert again.status_code == 202, again.text
    for map_id in ("waiting", "busy"):
        assert fleet.a.delete(f"/maps/{map_id}", headers=AUTH).status_code == 200
    _wait(lambda: not fleet.redis().exists(f"{NAMESPACE}:v1:build:busy"), 30, "busy build cancelled")


def test_failed_build_reports_its_reason_everywhere(fleet: Fleet) -> None:
    r = fleet.a.post("/maps", data={"map_id": "broken", "preset": "boreas"}, files=_archive(4, seed0=300, corrupt=2), headers=AUTH)
    assert r.status_code == 202, r.text  # the first scan is checked at once; the third only by the worker
    _wait(lambda: _state(fleet.b, "broken") == "failed", 60, "failed build on B", step_s=0.2)
    info = fleet.b.get("/maps/broken").json()
    assert f"{keyframe_time(2)}.png" in info["error"]
    assert fleet.a.post("/maps", data={"map_id": "broken", "preset": "boreas"}, files=_archive(4), headers=AUTH).status_code == 409
    assert fleet.a.delete("/maps/broken", headers=AUTH).status_code == 200
    _wait(lambda: fleet.b.get("/maps/broken").status_code == 404, 5, "failed map deleted on B")


def test_redis_down_503_on_shared_scans_localization_keeps_working(fleet: Fleet) -> None:
    _stop(fleet.redis_proc)
    up = fleet.a.post("/scans", files={"scan": ("q.png", _png(1, keyframe_time(1)))})
    # whatever the error body's shape (docs/SERVICE.md), it names the cause and what to do instead
    assert up.status_code == 503 and "shared_state_unavailable" in up.text and "inline" in up.text, up.text
    assert int(up.headers["Retry-After"]) > 0  # QA (session 20): the documented header was missing
    by_id = fleet.b.post("/localize", json={"map_id": "city", "scan_id": "1" * 32})
    assert by_id.status_code == 503 and "Retry-After" in by_id.headers
    res = fleet.b.post("/localize", data={"map_id": "city"}, files={"scan": ("q.png", _png(4, keyframe_time(4)))})
    assert res.status_code == 200 and res.json()["status"] == "localized"
    assert fleet.a.get("/maps").status_code == 200 and fleet.a.get("/readyz").status_code == 200
    assert fleet.a.get("/ui/api/maps/city/localizations").status_code == 503
    queued = fleet.a.post("/maps", data={"map_id": "later", "preset": "boreas"}, files=_archive(3), headers=AUTH)
    assert queued.status_code == 503 and "retry later" in queued.text, queued.text
    assert fleet.b.get("/maps/later").status_code == 404 and not any((fleet.maps_dir / ".build-queue").iterdir())
