"""Races of a fleet's map registry, replayed deterministically in one process: two replicas' registries
(``QueuedMapRegistry``) on one real ``redis-server`` and one shared maps folder, and the build worker's job
function (``service.worker.build_map_job``) called directly, with the racing request injected at the exact
point where QA's SIGSTOP / timing runs hit it (session 21, /tmp/qa_fleet):

1. a map deleted and registered again while a replica missed both events: that replica reopens the new file;
2. a map file upload and a build (or two uploads) of one id: the second gets 409; a map file installed under
   a building id fails the build (files cleaned up) and every replica serves the one file;
3. DELETE at the end of a build: the answered DELETE always wins (nothing stays installed);
4. Redis restarted without its data: job folders without a record are swept, the replica says so;
5. DELETE on one replica, then POST on another before its map sync ran: accepted;
6. DELETE of a build that finished since this replica last looked: deleted, not "being built".
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import shutil
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest
import redis

import service.core.jobs as jobs_module
import service.core.registry as registry_module
from maps.build import build_map
from maps.store import install_file
from reradar_core.io.datasets import mid_sweep_poses_in
from reradar_core.io.poses import PoseSequence
from reradar_core.io.presets import get_preset
from reradar_core.io.scan import RadarScan, encode_navtech_png_bytes
from service.core.config import Settings
from service.core.errors import ConflictError
from service.core.jobs import BuildQueue, QueuedMapRegistry, jobs_dir, sweep_orphan_jobs
from service.core.registry import MapRegistry
from service.core.shared_state import Keys, MapSync, connect

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import FakeExtractor, keyframe_time, make_scan  # noqa: E402
from test_ops_fleet import _free_port, _redis_server, _wait  # noqa: E402

pytest.importorskip("arq")


@pytest.fixture(scope="module")
def redis_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    root = tmp_path_factory.mktemp("races-redis")
    port = _free_port()
    proc = subprocess.Popen([_redis_server(), "--port", str(port), "--bind", "127.0.0.1", "--save", "",
                             "--appendonly", "no", "--dir", str(root)],
                            stdout=(root / "redis.log").open("wb"), stderr=subprocess.STDOUT)
    url = f"redis://127.0.0.1:{port}/0"

    def up() -> bool:
        try:
            return bool(redis.Redis.from_url(url).ping())
        except redis.RedisError:
            return False

    try:
        _wait(up, 20, "redis-server", step_s=0.05)
        yield url
    finally:
        proc.terminate()
        proc.wait(timeout=10)


@pytest.fixture(scope="module")
def map_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Two valid maps of different sizes (v1: 6 keyframes, v2: 4) and a file that is no map."""
    root = tmp_path_factory.mktemp("race-maps")
    out = {}
    for name, n, seed in (("v1", 6, 0), ("v2", 4, 50)):
        poses = np.column_stack([np.arange(n) * 30.0, np.zeros(n), np.zeros(n)])

        def scan(i: int, seed: int = seed) -> RadarScan:
            return make_scan(seed + i, keyframe_time(i))

        out[name] = build_map(root / f"{name}.h5", FakeExtractor(), scan, poses, radar_preset="boreas", name=name,
                              batch_size=4)
    (root / "junk.h5").write_bytes(b"not an HDF5 file" * 64)
    out["junk"] = root / "junk.h5"
    return out


@dataclass
class Fleet:
    """Two replicas' registries and a worker's context on one Redis namespace and one maps folder."""

    maps_dir: Path
    settings: Settings
    client: redis.Redis
    keys: Keys
    a: QueuedMapRegistry
    b: QueuedMapRegistry
    events: list[tuple[str, str]] = field(default_factory=list)

    @property
    def queue(self) -> BuildQueue:
        return self.a.queue

    def sync(self, registry: MapRegistry) -> MapSync:
        """The replica's map sync, not started: ``reconcile()`` is one pass (an event or the timer)."""
        extra = registry.reconcile_builds if isinstance(registry, QueuedMapRegistry) else None
        return MapSync(self.client, self.keys, registry, 60.0, "test", extra_reconcile=extra)

    def stage(self, registry: MapRegistry, source: Path) -> Path:
        staged = registry.staging_dir() / f"{uuid.uuid4().hex}.h5"
        shutil.copyfile(source, staged)
        return staged

    def queue_build(self, registry: QueuedMapRegistry, map_id: str, n: int = 3,
                    pose_track: PoseSequence | None = None) -> str:
        """``POST /maps`` with an archive of ``n`` scans (and the pose file's poses ``pose_track``) through
        ``registry``; returns the job id."""
        work = registry.staging_dir() / f"job-{uuid.uuid4().hex}"
        (work / "scans").mkdir(parents=True)
        paths = []
        for i in range(n):
            path = work / "scans" / f"{keyframe_time(i)}.png"
            path.write_bytes(encode_navtech_png_bytes(make_scan(100 + i, keyframe_time(i))))
            paths.append(path)
        poses = np.column_stack([np.arange(n) * 25.0, np.zeros(n), np.zeros(n)])
        registry.start_build(map_id, paths, poses, None, work, source="upload:test.zip", pose_track=pose_track)
        return self.record(map_id)["job_id"]

    def record(self, map_id: str) -> dict[str, str]:
        return self.queue.record(map_id)

    def worker_ctx(self) -> dict[str, Any]:
        return {"settings": self.settings, "queue": BuildQueue(self.client, self.keys, self.settings),
                "sync_redis": self.client, "keys": self.keys, "extractor": FakeExtractor(),
                "registry": MapRegistry(self.settings, FakeExtractor()), "origin": "test-worker", "job_try": 1}

    def run_job(self, map_id: str, job_id: str) -> str:
        from service.worker import build_map_job

        return asyncio.run(build_map_job(self.worker_ctx(), map_id, job_id))


@pytest.fixture
def fleet(redis_url: str, tmp_path: Path) -> Iterator[Fleet]:
    maps_dir = tmp_path / "maps"
    maps_dir.mkdir()
    namespace = f"races-{uuid.uuid4().hex[:8]}"
    settings = Settings(maps_dir=maps_dir, redis_url=redis_url, redis_namespace=namespace, load_demo_map=False,
                        build_batch_size=2)
    client = connect(redis_url)
    keys = Keys(namespace)
    events: list[tuple[str, str]] = []

    def replica() -> QueuedMapRegistry:
        reg = QueuedMapRegistry(settings, FakeExtractor(), BuildQueue(client, keys, settings),
                                publish=lambda op, map_id: events.append((op, map_id)))
        reg.load_all()
        return reg

    fl = Fleet(maps_dir, settings, client, keys, replica(), replica(), events)
    try:
        yield fl
    finally:
        fl.a.close()
        fl.b.close()
        client.close()


def _keyframes(registry: MapRegistry, map_id: str) -> int:
    return len(registry.ready(map_id))


# ---- 1. a replica that missed a DELETE + POST of one id reopens the new file --------------------------------
def test_replaced_map_file_is_reopened_by_a_replica_that_missed_the_events(
        fleet: Fleet, map_files: dict[str, Path]) -> None:
    """QA (session 21, HIGH): B, paused while A deleted 'city' and registered it again, served the old map (6
    keyframes, its unlinked file kept open) for good; the 5 s re-check only looked at whether city.h5 exists."""
    fleet.a.register_file("city", fleet.stage(fleet.a, map_files["v1"]))
    sync_b = fleet.sync(fleet.b)
    sync_b.reconcile()
    assert _keyframes(fleet.b, "city") == 6
    old_db = fleet.b.ready("city")
    fleet.a.delete("city")  # B misses the events of both
    fleet.a.register_file("city", fleet.stage(fleet.a, map_files["v2"]))
    assert _keyframes(fleet.a, "city") == 4
    sync_b.reconcile()
    assert _keyframes(fleet.b, "city") == 4 and fleet.b.ready("city") is not old_db
    sync_b.reconcile()  # the same file again: nothing is reopened
    assert fleet.b.get("city").db is fleet.b.ready("city")
    # a replacement that is not a valid map: failed with the reason, as a map file that fails to load
    broken = fleet.maps_dir / ".broken.tmp-test"
    shutil.copyfile(map_files["junk"], broken)
    os.replace(broken, fleet.maps_dir / "city.h5")
    sync_b.reconcile()
    entry = fleet.b.get("city")
    assert entry.state == "failed" and entry.error and str(fleet.maps_dir) not in entry.error
    shutil.copyfile(map_files["v1"], broken)  # and a valid one after it is served again
    os.replace(broken, fleet.maps_dir / "city.h5")
    sync_b.reconcile()
    assert _keyframes(fleet.b, "city") == 6


def test_single_process_registry_has_no_reload_path(map_files: dict[str, Path], tmp_path: Path) -> None:
    """Without Redis nothing reconciles the folder, so nothing reopens: the file a map was opened from is
    recorded all the same (``MapEntry.file_id``), from the staged file the install links in place."""
    reg = MapRegistry(Settings(maps_dir=tmp_path, load_demo_map=False), FakeExtractor())
    try:
        staged = reg.staging_dir() / "x.h5"
        shutil.copyfile(map_files["v1"], staged)
        entry = reg.register_file("solo", staged)
        assert entry.file_id == registry_module.file_identity(tmp_path / "solo.h5")
        assert reg.reopen_if_replaced("solo") is None  # same file
    finally:
        reg.close()


def test_a_map_file_placed_in_the_folder_is_read_through_in_a_child_process_once(
        map_files: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Session 22 (low, open until session 23): a map file placed straight into the maps folder was opened in the
    service's own process at start-up, so a crafted file that crashes the HDF5 library took the service down
    (uploads were already read in a child first). Now every file the service has not read through is probed in a
    child first (``probe_map``), once per file identity; uploads it probed are recorded too."""
    probed: list[str] = []
    real_probe = registry_module.probe_map

    def probe(path: Path) -> None:
        probed.append(Path(path).name)
        real_probe(path)

    monkeypatch.setattr(registry_module, "probe_map", probe)
    shutil.copyfile(map_files["v1"], tmp_path / "placed.h5")
    settings = Settings(maps_dir=tmp_path, load_demo_map=False)

    def start() -> MapRegistry:
        reg = MapRegistry(settings, FakeExtractor())
        reg.load_all()
        return reg

    reg = start()
    assert probed == ["placed.h5"] and len(reg.ready("placed")) == 6
    reg.register_file("uploaded", _staged(reg, map_files["v2"]))  # probed before its install
    assert probed == ["placed.h5", _STAGED_NAME]
    reg.close()
    reg = start()  # both read through before: opened without another child
    assert probed == ["placed.h5", _STAGED_NAME] and len(reg.ready("uploaded")) == 4
    reg.close()
    shutil.copyfile(map_files["v2"], tmp_path / ".swap.tmp-x")  # another file under the same name: probed again
    os.replace(tmp_path / ".swap.tmp-x", tmp_path / "placed.h5")
    reg = start()
    assert probed[-1] == "placed.h5" and len(probed) == 3 and len(reg.ready("placed")) == 4
    reg.close()

    def crash(path: Path) -> None:  # what probe_map says when the HDF5 library crashes the child on a file
        raise registry_module.MapFormatError(f"{path}: corrupt map file (the HDF5 library crashed reading it, "
                                             "signal 11)")

    monkeypatch.setattr(registry_module, "probe_map", crash)
    opened: list[Path] = []
    monkeypatch.setattr(MapRegistry, "_open", lambda self, path: opened.append(path))
    other = tmp_path / "other"
    other.mkdir()
    shutil.copyfile(map_files["v1"], other / "crafted.h5")
    reg = MapRegistry(Settings(maps_dir=other, load_demo_map=False), FakeExtractor())
    reg.load_all()
    entry = reg.get("crafted")
    assert entry.state == "failed" and entry.error and "crashed" in entry.error and str(other) not in entry.error
    assert opened == []  # never opened in this process
    reg.close()


_STAGED_NAME = "staged-upload.h5"


def _staged(registry: MapRegistry, source: Path) -> Path:
    staged = registry.staging_dir() / _STAGED_NAME
    shutil.copyfile(source, staged)
    return staged


def test_upload_in_flight_keeps_its_entry_through_a_map_sync_pass(
        fleet: Fleet, map_files: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    """A map sync pass during an upload (an event from another replica) took the upload's ``building`` entry,
    which has no build record, for a vanished build: the registered map was then served from a second copy
    and the upload's own database never closed."""
    real_probe = registry_module.probe_map

    def probe(path: Path) -> None:
        fleet.sync(fleet.a).reconcile()
        real_probe(path)

    monkeypatch.setattr(registry_module, "probe_map", probe)
    entry = fleet.a.register_file("mid", fleet.stage(fleet.a, map_files["v2"]))
    assert fleet.a.get("mid") is entry and entry.state == "ready"


# ---- 2. one id, one registration: claims and exclusive installs ----------------------------------------------
def test_map_file_upload_and_build_of_one_id_exclude_each_other(fleet: Fleet, map_files: dict[str, Path]) -> None:
    """QA (session 21, HIGH): an archive on A (202) and a map file on B (201) of one id were both accepted, and
    two map file uploads on A and B both got 201; the worker then installed over B's file: split for good."""
    fleet.queue_build(fleet.a, "mx")
    staged = fleet.stage(fleet.b, map_files["v1"])
    with pytest.raises(ConflictError, match="already being built"):
        fleet.b.register_file("mx", staged)
    assert not staged.exists() and not (fleet.maps_dir / "mx.h5").exists()
    # an upload in flight on B (claimed, not yet installed) refuses a build and another upload on A
    token = "upload-test"
    fleet.queue.claim_upload("up", token)
    with pytest.raises(ConflictError, match="being registered right now"):
        fleet.queue_build(fleet.a, "up")
    assert not any(d for d in jobs_dir(fleet.maps_dir).iterdir() if json.loads(
        (d / "spec.json").read_text())["map_id"] == "up")
    with pytest.raises(ConflictError, match="being registered right now"):
        fleet.a.register_file("up", fleet.stage(fleet.a, map_files["v2"]))
    assert 0 < cast(int, fleet.client.pttl(fleet.keys.build("up"))) <= 30_000  # a dead replica's claim expires
    fleet.queue.release_upload("up", token)
    # a finished upload frees the claim; the file then holds the id
    fleet.b.register_file("up", fleet.stage(fleet.b, map_files["v1"]))
    assert not fleet.client.exists(fleet.keys.build("up"))
    with pytest.raises(ConflictError, match="already exists"):
        fleet.queue_build(fleet.a, "up")


def test_upload_claim_outlives_its_ttl_while_the_upload_runs_and_expires_once_abandoned(
        fleet: Fleet, map_files: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    """QA (session 22, low): a replica that died mid-upload held the id for 300 s. The claim's TTL is now short
    and the uploading request renews it, so a check slower than the TTL keeps the id claimed to the end, and a
    claim nobody renews (its replica died) frees the id within the TTL."""
    monkeypatch.setattr(jobs_module, "UPLOAD_CLAIM_TTL_S", 0.6)  # renewed every 0.2 s
    real_probe = registry_module.probe_map
    seen: list[str] = []

    def slow_probe(path: Path) -> None:
        time.sleep(1.5)  # 2.5 TTLs: without renewal the claim would be gone
        with pytest.raises(ConflictError, match="being registered right now") as err:
            fleet.b.register_file("slow", fleet.stage(fleet.b, map_files["v2"]))
        seen.append(str(err.value))
        real_probe(path)

    monkeypatch.setattr(registry_module, "probe_map", slow_probe)
    entry = fleet.a.register_file("slow", fleet.stage(fleet.a, map_files["v1"]))
    assert entry.state == "ready" and len(seen) == 1 and len(fleet.a.ready("slow")) == 6
    assert not fleet.client.exists(fleet.keys.build("slow"))  # released at the end
    # a claim whose replica died (never renewed, never released) frees the id after the TTL
    fleet.queue.claim_upload("orphan", "upload-dead-replica")
    with pytest.raises(ConflictError, match="being registered right now"):
        fleet.queue_build(fleet.a, "orphan")
    time.sleep(0.8)
    assert not fleet.client.exists(fleet.keys.build("orphan"))
    fleet.queue_build(fleet.a, "orphan")
    assert fleet.record("orphan")["state"] == "queued"
    assert not fleet.queue.renew_upload("orphan", "upload-dead-replica")  # a build's claim is not the upload's


def test_install_never_replaces_a_map_file(fleet: Fleet, map_files: dict[str, Path]) -> None:
    """The last line of defence when the claim could not be taken (Redis down): the install is exclusive, and
    a failed install never deletes the other writer's file."""
    target = fleet.maps_dir / "mine.h5"
    shutil.copyfile(map_files["v1"], target)
    before = registry_module.file_identity(target)
    src = fleet.maps_dir / ".other.tmp-test"
    shutil.copyfile(map_files["v2"], src)
    with pytest.raises(FileExistsError):
        install_file(src, target, exclusive=True)
    assert registry_module.file_identity(target) == before and src.exists()
    # the registry's upload, past its id check (the file appeared after it): 409, the file untouched
    reg = MapRegistry(fleet.settings, FakeExtractor())
    try:
        staged = fleet.stage(reg, map_files["v2"])
        original = MapRegistry.check_free
        try:
            MapRegistry.check_free = lambda self, map_id: None  # type: ignore[method-assign]
            with pytest.raises(ConflictError, match="already exists"):
                reg.register_file("mine", staged)
        finally:
            MapRegistry.check_free = original  # type: ignore[method-assign]
        assert registry_module.file_identity(target) == before and not staged.exists()
    finally:
        reg.close()


def test_build_of_an_id_taken_meanwhile_fails_and_every_replica_serves_the_file(
        fleet: Fleet, map_files: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    import maps.build

    job_id = fleet.queue_build(fleet.a, "mx")
    fleet.sync(fleet.b).reconcile()
    assert fleet.b.get("mx").state == "building"
    real = maps.build.build_map

    def build_then_file_appears(out: Path, *args: Any, **kwargs: Any) -> Path:
        path = real(out, *args, **kwargs)
        # a map file installed under the id meanwhile (an upload that could not claim it: Redis was down)
        shutil.copyfile(map_files["v1"], fleet.maps_dir / ".racer.tmp-test")
        os.replace(fleet.maps_dir / ".racer.tmp-test", fleet.maps_dir / "mx.h5")
        return path

    monkeypatch.setattr(maps.build, "build_map", build_then_file_appears)
    uploaded = registry_module.file_identity(fleet.maps_dir / "mx.h5")
    assert fleet.run_job("mx", job_id) == "failed"
    rec = fleet.record("mx")
    assert rec["state"] == "failed" and "another map was registered as 'mx'" in rec["error"]
    assert str(fleet.maps_dir) not in rec["error"]
    assert not (jobs_dir(fleet.maps_dir) / job_id).exists()  # the build's files are cleaned up
    assert registry_module.file_identity(fleet.maps_dir / "mx.h5") != uploaded  # the racer's file, untouched
    for reg in (fleet.a, fleet.b):  # one map everywhere: the file
        fleet.sync(reg).reconcile()
        assert _keyframes(reg, "mx") == 6
    fleet.a.delete("mx")  # and DELETE frees the id (file and record)
    assert not (fleet.maps_dir / "mx.h5").exists() and not fleet.client.exists(fleet.keys.build("mx"))


def test_a_queued_build_checks_the_pose_clock_on_the_uploaded_pose_file(
        fleet: Fleet, monkeypatch: pytest.MonkeyPatch) -> None:
    """The worker's pose-clock check reads the pose file the upload sent (kept with the job), not the keyframe poses
    alone: between scans seconds apart those cut a corner's turn (test_service_pose_clock)."""
    import maps.build

    t = keyframe_time(0) + np.arange(-4, 40) * 250_000
    track = PoseSequence(t, np.column_stack([np.arange(44) * 2.5, np.sin(np.arange(44) / 5.0)]),
                         np.linspace(-1.0, 1.0, 44))
    job_id = fleet.queue_build(fleet.a, "clocked", pose_track=track)
    seen: list[Any] = []
    real = maps.build.build_map

    def build(*args: Any, **kwargs: Any) -> Path:
        seen.append(kwargs.get("pose_at"))
        return real(*args, **kwargs)

    monkeypatch.setattr(maps.build, "build_map", build)
    assert fleet.run_job("clocked", job_id) == "ready"
    assert seen[0] is not None
    at = keyframe_time(0) + np.array([0, 300_000, 1_700_000, 6_000_000])  # between and beyond the scans
    np.testing.assert_array_equal(seen[0](at), mid_sweep_poses_in(track, at, get_preset("boreas")))


# ---- 3. DELETE at the end of a build --------------------------------------------------------------------------
@pytest.mark.parametrize("when", ["after the last batch", "after the install"])
def test_delete_answered_at_the_end_of_a_build_always_wins(
        fleet: Fleet, monkeypatch: pytest.MonkeyPatch, when: str) -> None:
    """QA (session 21, MEDIUM): a DELETE just after the last batch answered 200, and the map was installed all
    the same (record ``ready`` with ``cancel=1``)."""
    import maps.build
    import service.worker as worker

    job_id = fleet.queue_build(fleet.a, "late")
    fleet.sync(fleet.b).reconcile()
    answered: list[str] = []

    def delete_on_b() -> None:
        answered.append(fleet.b.delete("late").state)

    if when == "after the last batch":
        real_build = maps.build.build_map

        def build(*args: Any, **kwargs: Any) -> Path:
            out = real_build(*args, **kwargs)
            delete_on_b()
            return out

        monkeypatch.setattr(maps.build, "build_map", build)
    else:
        real_install = worker.install_map_files

        def install(built: Path, target: Path, far_built: Path | None = None) -> None:
            real_install(built, target, far_built)
            delete_on_b()

        monkeypatch.setattr(worker, "install_map_files", install)
    events = fleet.client.pubsub(ignore_subscribe_messages=True)
    events.subscribe(fleet.keys.map_events)
    try:
        assert fleet.run_job("late", job_id) == "cancelled"
        published = []
        deadline = time.monotonic() + 0.5  # all published already; None also stands for skipped messages
        while time.monotonic() < deadline:
            if (msg := events.get_message(timeout=0.05)) is not None:
                published.append(json.loads(msg["data"])["op"])
    finally:
        events.close()
    assert answered == ["building"]  # the DELETE was answered as a cancel (200)
    assert not (fleet.maps_dir / "late.h5").exists() and not fleet.client.exists(fleet.keys.build("late"))
    assert not (jobs_dir(fleet.maps_dir) / job_id).exists()
    if when == "after the install":
        assert "deleted" in published  # replicas that loaded the installed map drop it
    for reg in (fleet.a, fleet.b):
        fleet.sync(reg).reconcile()
        assert "late" not in {e.map_id for e in reg.entries()}


def test_build_stopped_between_install_and_ready_is_finished_by_its_retry(
        fleet: Fleet, monkeypatch: pytest.MonkeyPatch) -> None:
    """The map file an attempt installed is its own on the retry (not "another map was registered"), and a
    DELETE that cancels the build before the retry removes it: taken off the queue (the retry waits there) or,
    with a worker on it already, flagged."""
    from arq import Retry

    from service.core.jobs import ARQ_IN_PROGRESS_PREFIX

    for map_id, cancel in (("again", None), ("dropped", "queued"), ("flagged", "running")):
        job_id = fleet.queue_build(fleet.a, map_id)
        fleet.sync(fleet.b).reconcile()  # B shows it building
        with monkeypatch.context() as m:
            def hiccup(self: BuildQueue, *args: Any) -> int:
                raise redis.ConnectionError("Redis restarting")

            m.setattr(BuildQueue, "mark_ready", hiccup)
            with pytest.raises(Retry):
                fleet.run_job(map_id, job_id)
        target = fleet.maps_dir / f"{map_id}.h5"
        assert target.is_file() and fleet.record(map_id)["state"] == "queued"
        if cancel == "running":
            fleet.client.set(ARQ_IN_PROGRESS_PREFIX + job_id, b"1")  # a worker dequeued the retry
        if cancel:
            assert fleet.b.delete(map_id).state == "building"  # answered as a cancel
        if cancel == "queued":  # no worker will run it: the DELETE removed everything
            assert not target.exists() and not fleet.client.exists(fleet.keys.build(map_id))
            assert not (jobs_dir(fleet.maps_dir) / job_id).exists()
            continue
        assert fleet.run_job(map_id, job_id) == ("cancelled" if cancel else "ready")
        assert target.is_file() is (cancel is None)
        assert fleet.record(map_id).get("state") == (None if cancel else "ready")


def test_redis_stall_during_a_build_does_not_cost_the_attempt(fleet: Fleet, monkeypatch: pytest.MonkeyPatch,
                                                               caplog: pytest.LogCaptureFixture) -> None:
    """QA (session 22, low): a Redis stall while a build recorded its progress failed the attempt (one of
    ``build_max_tries``). Progress is best effort now; the build goes on and is ``ready`` after one attempt."""
    job_id = fleet.queue_build(fleet.a, "stall", n=5)  # batches of 2: progress is recorded three times
    real_update = BuildQueue.update
    stalls = []

    def update(self: BuildQueue, map_id: str, /, **fields: object) -> None:
        if "scans_done" in fields and fields["scans_done"] == 2:
            stalls.append(map_id)
            raise redis.TimeoutError("Timeout reading from socket")
        real_update(self, map_id, **fields)

    monkeypatch.setattr(BuildQueue, "update", update)
    with caplog.at_level(logging.WARNING, logger="service.worker"):
        assert fleet.run_job("stall", job_id) == "ready"
    assert stalls == ["stall"] and any("progress not recorded" in r.getMessage() for r in caplog.records)
    rec = fleet.record("stall")
    assert rec["state"] == "ready" and rec["attempts"] == "1" and rec["scans_done"] == "5"
    fleet.sync(fleet.b).reconcile()
    assert _keyframes(fleet.b, "stall") == 5


def test_cancel_never_flags_a_build_already_ready(fleet: Fleet) -> None:
    job_id = fleet.queue_build(fleet.a, "done")
    fleet.queue.update("done", state="running")
    assert fleet.queue.mark_ready("done", job_id, 3) == 1
    assert fleet.queue.cancel("done") == (False, None) and fleet.record("done").get("cancel") == "0"
    assert fleet.queue.mark_ready("done", "another-job", 3) == -1


# ---- 6. DELETE of a build that finished since the replica last looked -----------------------------------------
def test_delete_of_a_build_finished_meanwhile_deletes_the_map(fleet: Fleet) -> None:
    """QA (session 21, LOW): a DELETE just after a build finished answered the single-process 409 "is being
    built; wait for the job to finish" (the record was no longer active, this replica's entry still was)."""
    job_id = fleet.queue_build(fleet.a, "fresh")
    fleet.sync(fleet.b).reconcile()
    assert fleet.run_job("fresh", job_id) == "ready"
    assert fleet.b.get("fresh").state == "building"  # B has not seen the "built" event yet
    deleted = fleet.b.delete("fresh")
    assert deleted.state == "ready"
    assert not (fleet.maps_dir / "fresh.h5").exists() and not fleet.client.exists(fleet.keys.build("fresh"))
    fleet.sync(fleet.a).reconcile()
    assert "fresh" not in {e.map_id for e in fleet.a.entries()}


# ---- 4. Redis restarted without its data ----------------------------------------------------------------------
def test_job_folders_without_a_record_are_swept_and_the_replica_warns(
        fleet: Fleet, caplog: pytest.LogCaptureFixture) -> None:
    """QA (session 21, MEDIUM/LOW): Redis restarted without persistence mid-build: the build vanished (404,
    never ``failed``) and ``.build-queue/<job_id>/`` with its scans stayed forever. Now it is ``failed``."""
    kept = fleet.queue_build(fleet.a, "kept")
    lost = fleet.queue_build(fleet.a, "lost")
    fleet.queue.remove("lost")  # what a Redis restart without its data does to the record
    young = jobs_dir(fleet.maps_dir) / "being-staged"  # an API replica between staging and the record
    young.mkdir()
    (young / "spec.json").write_text("{}")
    assert sweep_orphan_jobs(fleet.queue, fleet.maps_dir, 300.0) == []  # nothing old enough yet
    assert sorted(sweep_orphan_jobs(fleet.queue, fleet.maps_dir, 300.0, now=time.time() + 301)) == \
        sorted([lost, "being-staged"])
    assert (jobs_dir(fleet.maps_dir) / kept).is_dir() and not (jobs_dir(fleet.maps_dir) / lost).exists()
    # the replica that showed "gone" building finds its record gone: failed with the reason (QA session 22: it
    # answered 404), on every replica, and a DELETE frees the id
    gone_job = fleet.queue_build(fleet.b, "gone")
    fleet.sync(fleet.a).reconcile()
    fleet.queue.remove("gone")
    with caplog.at_level(logging.WARNING, logger="service.core.jobs"):
        fleet.b.reconcile_builds()
        fleet.b.reconcile_builds()  # a second pass keeps it (the record it wrote)
        fleet.a.reconcile_builds()  # the other replica, which showed it building too, takes the failed record
    for replica in (fleet.a, fleet.b):
        entry = replica.get("gone")
        assert entry.state == "failed" and entry.error and "lost" in entry.error and "DELETE /maps/gone" in entry.error
    assert fleet.record("gone")["job_id"] == f"lost-{gone_job}"
    assert sum("gone" in r.getMessage() and "vanished" in r.getMessage() for r in caplog.records) == 1
    assert not fleet.queue.record_lost("gone", gone_job, 0, 3, "again")  # written once, whoever comes second
    caplog.clear()
    # its job folder is an orphan for the sweep; a DELETE frees the id
    assert gone_job in sweep_orphan_jobs(fleet.queue, fleet.maps_dir, 300.0, now=time.time() + 301)
    fleet.a.delete("gone")
    assert not fleet.client.exists(fleet.keys.build("gone"))
    fleet.b.reconcile_builds()
    assert "gone" not in {e.map_id for e in fleet.b.entries()}
    fleet.queue_build(fleet.b, "gone")
    assert fleet.b.get("kept").state == "building"
    fleet.a.delete("kept")  # cancelled while queued: its files go before its record
    with caplog.at_level(logging.WARNING, logger="service.core.jobs"):
        fleet.b.reconcile_builds()
    assert "kept" not in {e.map_id for e in fleet.b.entries()}
    assert not any("vanished" in r.getMessage() for r in caplog.records)


# ---- 5. DELETE on one replica, POST on another before its map sync ran ----------------------------------------
def test_post_right_after_a_delete_elsewhere_is_accepted(fleet: Fleet, map_files: dict[str, Path]) -> None:
    """QA (session 21, LOW): DELETE on B then POST on A within the 2 s propagation window: 409 "already exists"
    from A's stale view."""
    fleet.a.register_file("xr", fleet.stage(fleet.a, map_files["v1"]))
    fleet.sync(fleet.b).reconcile()
    fleet.b.delete("xr")  # A has not seen the "deleted" event yet
    assert fleet.a.get("xr").state == "ready"
    entry = fleet.a.register_file("xr", fleet.stage(fleet.a, map_files["v2"]))
    assert entry.state == "ready" and _keyframes(fleet.a, "xr") == 4


# ---- 7. a build with its far-view companion (POST /maps far_view=true) on the queue ---------------------------
@pytest.mark.parametrize("delete_after_install", [False, True])
def test_a_far_view_build_installs_the_companion_first_and_every_replica_serves_it(
        fleet: Fleet, monkeypatch: pytest.MonkeyPatch, delete_after_install: bool) -> None:
    from test_service_far_view import NearFake, far_scan

    import service.worker as worker

    def replica() -> QueuedMapRegistry:  # replicas with a model that has a far view
        reg = QueuedMapRegistry(fleet.settings, NearFake(), BuildQueue(fleet.client, fleet.keys, fleet.settings),
                                publish=lambda op, map_id: fleet.events.append((op, map_id)))
        reg.load_all()
        return reg

    a, b = replica(), replica()
    try:
        n = 4
        work = a.staging_dir() / f"job-{uuid.uuid4().hex}"
        (work / "scans").mkdir(parents=True)
        paths = []
        for i in range(n):
            paths.append(work / "scans" / f"{keyframe_time(i)}.png")
            paths[-1].write_bytes(encode_navtech_png_bytes(far_scan(i, keyframe_time(i))))
        poses = np.column_stack([np.arange(n) * 40.0, np.zeros(n), np.zeros(n)])
        entry = a.start_build("moor", paths, poses, "boreas", work, source="upload:test.zip", far_view=True)
        assert entry.far_view and entry.scans_total == 2 * n
        rec = fleet.record("moor")
        assert rec["far_view"] == "1" and rec["scans_total"] == str(2 * n)
        fleet.sync(b).reconcile()
        assert b.get("moor").state == "building" and b.get("moor").far_view  # every replica says so
        installed: list[tuple[str, bool]] = []  # (file installed, its companion beside it already)
        real_install = registry_module.install_file

        def install(src: Path, dst: Path, exclusive: bool = False) -> Path:
            installed.append((Path(dst).name, (Path(dst).parent / "moor.far.h5").is_file()))
            return real_install(src, dst, exclusive=exclusive)

        monkeypatch.setattr(registry_module, "install_file", install)
        if delete_after_install:
            real_files = worker.install_map_files

            def install_then_delete(built: Path, target: Path, far_built: Path | None = None) -> None:
                real_files(built, target, far_built)
                assert b.delete("moor").state == "building"  # answered as a cancel

            monkeypatch.setattr(worker, "install_map_files", install_then_delete)
        ctx = {**fleet.worker_ctx(), "extractor": NearFake(), "registry": MapRegistry(fleet.settings, NearFake())}
        outcome = asyncio.run(worker.build_map_job(ctx, "moor", rec["job_id"]))
        assert installed == [("moor.h5", True)]  # a replica that loads the map finds its companion
        if delete_after_install:  # the cancelled build leaves neither file
            assert outcome == "cancelled"
            assert not (fleet.maps_dir / "moor.h5").exists() and not (fleet.maps_dir / "moor.far.h5").exists()
            return
        assert outcome == "ready" and fleet.record("moor")["scans_done"] == str(2 * n)
        for reg in (a, b):
            fleet.sync(reg).reconcile()
            assert reg.get("moor").state == "ready" and reg.serves_far_view("moor")
        b.delete("moor")
        assert not (fleet.maps_dir / "moor.h5").exists() and not (fleet.maps_dir / "moor.far.h5").exists()
    finally:
        a.close()
        b.close()
