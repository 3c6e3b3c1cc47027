"""Map upload hardening (QA session 21, F1/F2/F4/F8-F10 and L2): a map the running model cannot use, a damaged
HDF5 file, a declared-huge dataset, bad timestamps or descriptors are refused at ``POST /maps`` with a 422
``map_format`` naming what is wrong (never a 500, never accepted to fail every ``/localize``), and nothing of the
refused upload is stored. Failed builds report the error's message without the Python class name."""

from __future__ import annotations

import asyncio
import io
import re
import shutil
import sys
import time
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import h5py
import httpx
import numpy as np
import pytest

from maps.store import read_metadata
from reradar_core.errors import MapFormatError, ScanFormatError
from reradar_core.io.scan import RadarScan, encode_navtech_png_bytes
from service.core.config import Settings
from service.core.errors import PROBLEM_MEDIA_TYPE, ConflictError
from service.core.registry import MapRegistry, build_failure_message
from service.demo import serve_in_thread

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import (  # noqa: E402
    API_KEY,
    FakeExtractor,
    damaged_png,
    keyframe_poses,
    keyframe_time,
    make_scan,
    register_map_file,
    started_app,
)

AUTH = {"X-API-Key": API_KEY}
Edit = Callable[[h5py.File], object]


class LocalDimExtractor(FakeExtractor):
    """The fake network, stating its local descriptor length as the real one does (``local_dim``)."""

    local_dim = 16


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[httpx.Client, Path]]:
    """A live server whose extractor states both descriptor lengths (D 32, C 16); yields (client, maps dir)."""
    maps_dir = tmp_path_factory.mktemp("maps")
    settings = Settings(maps_dir=maps_dir, load_demo_map=False, api_key=API_KEY, max_upload_mb=3.0,
                        max_map_upload_mb=8.0, torch_threads=1)
    with serve_in_thread(settings, LocalDimExtractor()) as url, httpx.Client(base_url=url, timeout=120) as client:
        yield client, maps_dir


def _variant(fake_map: Path, tmp_path: Path, name: str, edit: Edit) -> Path:
    path = tmp_path / f"{name}.h5"
    shutil.copyfile(fake_map, path)
    with h5py.File(path, "r+") as f:
        edit(f)
    return path


def _replace(name: str, data: Any = None, **kw: Any) -> Edit:
    def edit(f: h5py.File) -> None:
        del f[name]
        f.create_dataset(name, data=data, **kw)
    return edit


def _local_width(width: int, attr: int | None = None) -> Edit:
    def edit(f: h5py.File) -> None:
        if attr is not None:
            f.attrs["local_descriptor_dim"] = attr
        for name in f["keyframes"]:
            grp = f["keyframes"][name]
            k = grp["keypoints_xy_m"].shape[0]
            del grp["local_descriptors"]
            grp.create_dataset("local_descriptors", data=np.full((k, width), 0.5, np.float16))
    return edit


def _descriptor_dim(dim: int) -> Edit:
    def edit(f: h5py.File) -> None:
        g = f["global_descriptors"][:, :dim] + 1e-3
        f.attrs["descriptor_dim"] = dim
        _replace("global_descriptors", (g / np.linalg.norm(g, axis=1, keepdims=True)).astype(np.float32))(f)
    return edit


def _keyframe_dataset(f: h5py.File) -> None:
    del f["keyframes/000002"]
    f["keyframes"].create_dataset("000002", data=[1])


def _timestamp_bomb(f: h5py.File) -> None:
    del f["timestamps_us"]
    f.create_dataset("timestamps_us", shape=(200_000_000,), dtype=np.int64, chunks=(1 << 20,), compression="gzip")


def _nan_timestamps(f: h5py.File) -> None:
    _replace("timestamps_us", np.full(len(f["poses"]), np.nan))(f)


def _equal_timestamps(f: h5py.File) -> None:
    _replace("timestamps_us", np.full(len(f["poses"]), keyframe_time(0), np.int64))(f)


def _huge_descriptors(f: h5py.File) -> None:
    _replace("global_descriptors", np.full(f["global_descriptors"].shape, 1e30, np.float32))(f)


UPLOADS: dict[str, tuple[Edit, str]] = {
    "local-dim": (_local_width(4, attr=4), r"local descriptors have 4 values \(local_descriptor_dim\) but the running "
                                           "model 'fake-extractor' computes 16"),
    "local-width": (_local_width(4), r"local_descriptors' has shape \(\d+, 4\), expected \(\d+, 16\)"),
    "descriptor-dim": (_descriptor_dim(8), r"global descriptors have 8 values \(descriptor_dim\) but the running "
                                           "model 'fake-extractor' computes 32"),
    "preset": (lambda f: f.attrs.__setitem__("radar_preset", "bogus"), "radar_preset 'bogus' is not a known"),
    "keyframe-dataset": (_keyframe_dataset, "'/keyframes/000002' is not a group"),
    "timestamp-bomb": (_timestamp_bomb, r"'/timestamps_us' has shape \(200000000,\), expected \(6,\)"),
    "timestamps-nan": (_nan_timestamps, "'/timestamps_us' has dtype float64, expected int64"),
    "timestamps-equal": (_equal_timestamps, f"timestamp {keyframe_time(0)} us appears more than once"),
    "descriptors-huge": (_huge_descriptors, "global descriptors must be L2-normalised"),
}


def _refused(client: httpx.Client, maps_dir: Path, map_id: str, data: bytes) -> str:
    """POST ``data`` as map ``map_id``: a 422 ``map_format`` problem; nothing stored. Returns the detail."""
    r = client.post("/maps", data={"map_id": map_id}, files={"map_file": ("m.h5", data)}, headers=AUTH)
    assert r.status_code == 422, r.text
    assert r.headers["content-type"] == PROBLEM_MEDIA_TYPE
    body = r.json()
    assert body["error"] == "map_format"
    detail = body["detail"]
    assert detail.startswith("the uploaded map: ") and "/tmp" not in detail and str(maps_dir) not in detail
    assert client.get(f"/maps/{map_id}").status_code == 404
    assert not (maps_dir / f"{map_id}.h5").exists() and not any((maps_dir / ".staging").glob("*.h5"))
    return detail


@pytest.mark.parametrize("case", sorted(UPLOADS))
def test_unusable_map_uploads_are_422_map_format(live: tuple[httpx.Client, Path], fake_map: Path,
                                                 tmp_path: Path, case: str) -> None:
    client, maps_dir = live
    edit, match = UPLOADS[case]
    detail = _refused(client, maps_dir, f"bad-{case}", _variant(fake_map, tmp_path, case, edit).read_bytes())
    assert re.search(match, detail), detail


def test_damaged_hdf5_uploads_are_422_map_format(live: tuple[httpx.Client, Path], fake_map: Path) -> None:
    """QA F2b: the demo map's superblock with the rest zeroed answered 500 ("Link visitation failed"); a damaged
    global heap (where the text attributes live) made the HDF5 library spin forever."""
    client, maps_dir = live
    data = fake_map.read_bytes()
    detail = _refused(client, maps_dir, "zeroed", data[:2048] + bytes(len(data) - 2048))
    assert "corrupt map file" in detail
    heap = data.index(b"GCOL")
    spin = data[:heap + 16] + bytes(16) + data[heap + 32:]  # first heap object: index 0, size 0
    assert "global heap at byte" in _refused(client, maps_dir, "heap", spin)


def test_valid_maps_still_register_and_localize(live: tuple[httpx.Client, Path], fake_map: Path,
                                                tmp_path: Path) -> None:
    """The builder's maps (conftest ``fake_map``: boreas, D 32, C 16) and valid variations (keyframes in another
    order than time; the preset a build without one records) are accepted, and localize."""
    client, _ = live
    register_map_file(client, fake_map, "good")

    def reorder(f: h5py.File) -> None:
        _replace("timestamps_us", f["timestamps_us"][()][::-1].copy())(f)
        f.attrs["radar_preset"] = "unknown"

    register_map_file(client, _variant(fake_map, tmp_path, "reordered", reorder), "reordered")
    png = encode_navtech_png_bytes(make_scan(3, keyframe_time(3)))
    r = client.post("/localize", data={"map_id": "good"}, files={"scan": ("s.png", png)})
    assert r.status_code == 200, r.text
    for map_id in ("good", "reordered"):
        assert client.delete(f"/maps/{map_id}", headers=AUTH).status_code == 200


def test_registry_refuses_stored_maps_the_model_cannot_use(fake_map: Path, tmp_path: Path) -> None:
    """A map already in the maps folder that the running model cannot use is listed ``failed`` with the reason
    (no server folder in it), its file kept; the others load."""
    maps_dir = tmp_path / "maps"
    maps_dir.mkdir()
    shutil.copyfile(fake_map, maps_dir / "good.h5")
    _variant(fake_map, maps_dir, "narrow", _local_width(4, attr=4))
    registry = MapRegistry(Settings(maps_dir=maps_dir, load_demo_map=False), LocalDimExtractor())
    try:
        registry.load_all()
        assert registry.get("good").state == "ready"
        narrow = registry.get("narrow")
        assert narrow.state == "failed" and (narrow.path).exists()
        assert narrow.error is not None and narrow.error.startswith("narrow.h5: the map's local descriptors have 4")
        assert str(tmp_path) not in narrow.error
        with pytest.raises(MapFormatError, match="computes 16"):
            registry.check_compatible(read_metadata(maps_dir / "narrow.h5"), maps_dir / "narrow.h5")
    finally:
        registry.close()


# ---- L2: failed-build messages --------------------------------------------------------------------------------

def test_build_failure_message_is_the_message_of_input_errors() -> None:
    assert build_failure_message(ScanFormatError("1600000018000000.png: not a PNG")) == "1600000018000000.png: not a PNG"
    assert build_failure_message(OSError(28, "No space left on device")) == "[Errno 28] No space left on device"
    assert build_failure_message(ValueError("bad value")) == "bad value"
    assert build_failure_message(KeyError("x")) == "KeyError: 'x'"  # a bug: its class says what happened
    assert build_failure_message(RuntimeError()) == "RuntimeError"
    # the service's own refusals say what is wrong (QA session 41: "ConflictError: map 'cc' already exists; ...")
    assert build_failure_message(ConflictError("map 'cc' already exists")) == "map 'cc' already exists"


def _archive(corrupt: int, n: int = 4, bad: bytes = b"not a png at all") -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for i in range(n):
            data = bad if i == corrupt else encode_navtech_png_bytes(make_scan(i, keyframe_time(i)))
            zf.writestr(f"{keyframe_time(i)}.png", data)
    return buf.getvalue()


def _poses_csv(n: int = 4) -> bytes:
    poses = keyframe_poses()[:n]
    rows = [f"{keyframe_time(i) / 1e6:.6f},{poses[i, 0]:.6f},{poses[i, 1]:.6f},{poses[i, 2]:.6f}" for i in range(n)]
    return ("t_s,x,y,yaw\n" + "\n".join(rows) + "\n").encode()


def test_failed_build_reports_the_message_without_the_class(live: tuple[httpx.Client, Path]) -> None:
    """QA L2: GET /maps/{id} of a failed build showed ``ScanFormatError: 1600000018000000.png: ...``."""
    client, _ = live
    # a file no decoder reads is refused at upload (QA session 40: it failed the build when the build reached it)
    files = {"archive": ("a.zip", _archive(corrupt=2)), "poses": ("p.csv", _poses_csv())}
    r = client.post("/maps", data={"map_id": "broken", "preset": "boreas"}, files=files, headers=AUTH)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert detail.startswith(f"scan archive member {keyframe_time(2)}.png: "), detail
    assert "Error:" not in detail and "/tmp" not in detail
    # another radar's scan among them (its time reads at upload) is refused at upload too, naming both layouts
    # (QA session 40: it failed the build when the build reached it)
    other = encode_navtech_png_bytes(RadarScan.from_power(np.zeros((400, 3768), np.float32), "oxford",
                                                          start_time_us=keyframe_time(2)))
    files = {"archive": ("a.zip", _archive(corrupt=2, bad=other)), "poses": ("p.csv", _poses_csv())}
    r = client.post("/maps", data={"map_id": "broken", "preset": "boreas"}, files=files, headers=AUTH)
    assert r.status_code == 422, r.text
    assert r.json()["detail"] == (
        "the archive holds scans of 2 radar layouts: 3 of 400 azimuths x 3360 range bins (e.g. "
        f"{keyframe_time(0)}.png) and 1 of 400 x 3768 (e.g. {keyframe_time(2)}.png); one map is built from one "
        "radar's scans: send them in separate maps, or convert them (`reradar import-scans`)")
    # a scan whose data is damaged past its first rows (header and time read at upload) fails the build, which says why
    files = {"archive": ("a.zip", _archive(corrupt=2, bad=damaged_png(make_scan(2, keyframe_time(2))))),
             "poses": ("p.csv", _poses_csv())}
    r = client.post("/maps", data={"map_id": "broken", "preset": "boreas"}, files=files, headers=AUTH)
    assert r.status_code == 202, r.text
    for _ in range(600):
        info = client.get("/maps/broken").json()
        if info["state"] != "building":
            break
        time.sleep(0.1)
    assert info["state"] == "failed", info
    assert info["error"].startswith(f"{keyframe_time(2)}.png: "), info["error"]
    assert "Error:" not in info["error"] and "/tmp" not in info["error"]
    assert client.delete("/maps/broken", headers=AUTH).status_code == 200


class _Queue:
    """The worker's view of a build record (``BuildQueue``): what ``_fail`` writes."""

    def __init__(self, attempts: int) -> None:
        self.attempts = attempts
        self.updates: list[dict[str, object]] = []

    def record(self, map_id: str) -> dict[str, str]:
        return {"attempts": str(self.attempts)}

    def update(self, map_id: str, /, **fields: object) -> None:
        self.updates.append(fields)


@pytest.mark.parametrize(("exc", "error"), [
    (ScanFormatError("1600000018000000.png: not a PNG"), "1600000018000000.png: not a PNG"),
    (RuntimeError("boom"), "RuntimeError: boom (after 3 attempts)"),
])
def test_worker_failed_build_reports_the_message_without_the_class(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path, exc: Exception, error: str) -> None:
    pytest.importorskip("arq")
    import service.worker as worker

    def build(ctx: dict[str, Any], map_id: str, job_id: str) -> str:
        raise exc

    monkeypatch.setattr(worker, "_build", build)
    queue = _Queue(attempts=3)
    ctx = {"queue": queue, "settings": Settings(maps_dir=tmp_path, build_max_tries=3),
           "registry": SimpleNamespace(maps_dir=tmp_path), "keys": SimpleNamespace(map_events="events"),
           "sync_redis": SimpleNamespace(publish=lambda channel, message: 0), "origin": "test"}
    assert asyncio.run(worker.build_map_job(ctx, "m", "job")) == "failed"
    assert queue.updates[-1] == {"state": "failed", "error": error}


def test_a_pose_file_over_its_own_limit_is_a_413_and_leaves_nothing(tmp_path: Path) -> None:
    """QA session 41: a pose file was bounded only by the 512 MB body limit; reading one keeps ~3x its size."""
    maps_dir = tmp_path / "maps"
    with started_app(maps_dir, max_pose_file_mb=0.001) as client:  # 1,048 bytes
        big = _poses_csv(4) + b"".join(b"# padding line of a pose file that is far too long\n" for _ in range(40))
        files = {"archive": ("a.zip", _archive(corrupt=-1)), "poses": ("p.csv", big)}
        r = client.post("/maps", data={"map_id": "big", "preset": "boreas"}, files=files, headers=AUTH)
        assert r.status_code == 413, r.text
        assert r.json()["detail"] == (
            "the 'poses' file is larger than RERADAR_MAX_POSE_FILE_MB (0.001 MB): send the poses at the scans' rate "
            "or near it (a Boreas applanix/radar_poses.csv, ~0.15 MB per hour), not a high-rate log")
        assert client.get("/maps/big", headers=AUTH).status_code == 404
        assert not list((maps_dir / ".staging").glob("*"))  # the upload's files are removed
        files = {"archive": ("a.zip", _archive(corrupt=-1)), "poses": ("p.csv", _poses_csv(4))}
        r = client.post("/maps", data={"map_id": "big", "preset": "boreas"}, files=files, headers=AUTH)
        assert r.status_code == 202, r.text  # within the limit: built
