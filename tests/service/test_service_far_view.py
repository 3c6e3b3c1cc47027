"""A map's far-view companion (``build-map --far-view``): built beside the map, served with it, used for the
answers the map's own view refuses, deleted with it, and never served for another map."""

from __future__ import annotations

import io
import shutil
import sys
import time
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from pydantic import SecretStr

from maps.build import build_map
from maps.database import MapDatabase
from maps.paths import far_view_path
from maps.store import open_map
from reradar_core.errors import ConfigError, MapFormatError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.cartesian import CartesianConfig
from reradar_core.io.scan import RadarScan, encode_navtech_png_bytes
from reradar_core.localization import FarViewConfig, PosePrior
from service.core.config import Settings
from service.core.errors import ConflictError
from service.core.registry import MapRegistry
from service.demo import serve_in_thread
from service.main import create_app

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import (  # noqa: E402
    API_KEY,
    FakeExtractor,
    keyframe_poses,
    keyframe_time,
    started_app,
    upload_map_file,
)

NEAR_REACH_M = 64.0


class FarFake(FakeExtractor):
    """The fake's far view: every return of the scan (the radar's whole range)."""

    model_id = "fake-extractor-in257"
    cartesian = CartesianConfig(257, 1.28)


class NearFake(FakeExtractor):
    """The fake with a near view: landmarks within 64 m only (the paper's image), and a far view."""

    def describe(self, scan: RadarScan) -> ScanFeatures:
        f = super().describe(scan)
        keep = np.hypot(f.keypoints_xy_m[:, 0], f.keypoints_xy_m[:, 1]) <= NEAR_REACH_M
        return ScanFeatures(f.global_descriptor, f.keypoints_xy_m[keep], f.local_descriptors[keep], f.timestamp_us)

    def with_view(self, cartesian: CartesianConfig) -> FarFake:
        assert (cartesian.width_px, cartesian.resolution_m) == (257, 1.28)
        return FarFake()


def far_scan(seed: int, t_us: int) -> RadarScan:
    """Open land: 40 bright returns, all beyond the near view's 64 m (bins 1,200-3,300 at 0.0596 m)."""
    rng = np.random.default_rng(seed)
    power = np.zeros((400, 3360), np.float32)
    power[rng.integers(0, 400, 40), rng.choice(np.arange(1200, 3300), 40, replace=False)] = 1.0
    return RadarScan.from_power(power, "boreas", start_time_us=t_us)


def build_open_land_map(out: Path, extractor: NearFake) -> Path:
    """A map of ``far_scan`` keyframes (open land) at ``out`` with its far-view companion, described by ``extractor``."""
    return build_map(out, extractor, lambda i: far_scan(i, keyframe_time(i)), keyframe_poses(),
                     radar_preset="boreas", name=out.stem, batch_size=4, far_view=FarViewConfig())


@pytest.fixture(scope="module")
def far_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_open_land_map(tmp_path_factory.mktemp("far") / "open.h5", NearFake())


def test_build_writes_the_companion_under_the_far_views_model(far_map: Path, tmp_path: Path) -> None:
    far = far_view_path(far_map)
    assert far.name == "open.far.h5" and far.is_file()
    with open_map(far_map, "fake-extractor", "f" * 64) as near_kf, open_map(far, "fake-extractor-in257", "f" * 64) as far_kf:
        assert len(near_kf) == len(far_kf) == len(keyframe_poses())
        np.testing.assert_array_equal(near_kf.poses, far_kf.poses)
        np.testing.assert_array_equal(near_kf.timestamps_us, far_kf.timestamps_us)
        assert len(near_kf.read_keyframe(1).keypoints_xy_m) == 0  # nothing within 64 m
        assert len(far_kf.read_keyframe(1).keypoints_xy_m) > 20
    # rebuilt without --far-view: the old companion would describe another map, so it goes
    out = tmp_path / "m.h5"
    shutil.copy(far_map, out)
    shutil.copy(far, far_view_path(out))
    build_map(out, NearFake(), lambda i: far_scan(i, keyframe_time(i)), keyframe_poses(), radar_preset="boreas",
              overwrite=True)
    assert out.is_file() and not far_view_path(out).exists()
    with pytest.raises(ConfigError, match="far view"):
        build_map(tmp_path / "x.h5", FakeExtractor(), lambda i: far_scan(i, keyframe_time(i)), keyframe_poses(),
                  radar_preset="boreas", far_view=FarViewConfig())


def test_a_refused_answer_is_given_by_the_far_view(far_map: Path) -> None:
    near_db = MapDatabase.open(far_map, "fake-extractor", "f" * 64)
    far_db = MapDatabase.open(far_view_path(far_map), "fake-extractor-in257", "f" * 64)
    try:
        near_db.attach_far(far_db)
        scan = far_scan(3, keyframe_time(3) + 7)
        alone = near_db.localize(NearFake().describe(scan))
        assert alone.status == "not_localized"  # no landmark within 64 m
        calls: list[int] = []

        def far_features() -> ScanFeatures:
            calls.append(1)
            return FarFake().describe(scan)

        answer = near_db.localize_views(NearFake().describe(scan), far_features)
        assert calls == [1] and answer.view == "far" and answer.result.localized
        assert answer.result.best.keyframe_id == 3
        np.testing.assert_allclose(answer.result.T_map_query[:2], keyframe_poses()[3, :2], atol=0.5)
        # without the query's far features the map's own answer stands
        assert near_db.localize_views(NearFake().describe(scan), None).view == "near"
        # a tracked request with nothing to register near its prior falls back to the global answer, and that
        # refused one to the far view
        prior = PosePrior(keyframe_poses()[3].copy(), 2.0, 0.05)
        tracked = near_db.track_views(NearFake().describe(scan), prior, far_features)
        assert tracked.near_result.mode == "global" and tracked.view == "far" and tracked.result.localized
        assert tracked.result.best.keyframe_id == 3
    finally:
        near_db.close()  # closes the attached far view too


def test_a_companion_of_another_map_is_not_attached(far_map: Path, tmp_path: Path) -> None:
    other = build_map(tmp_path / "other.h5", FarFake(), lambda i: far_scan(i, keyframe_time(i) + 1),
                      keyframe_poses(), radar_preset="boreas")
    near_db = MapDatabase.open(far_map, "fake-extractor", "f" * 64)
    other_db = MapDatabase.open(other, "fake-extractor-in257", "f" * 64)
    try:
        with pytest.raises(MapFormatError, match="does not hold the keyframes"):
            near_db.attach_far(other_db)
        assert near_db.far is None
    finally:
        other_db.close()
        near_db.close()


def test_the_service_serves_the_companion_and_deletes_it_with_the_map(far_map: Path, tmp_path: Path) -> None:
    maps_dir = tmp_path / "maps"
    maps_dir.mkdir()
    shutil.copy(far_map, maps_dir / "open.h5")
    shutil.copy(far_view_path(far_map), maps_dir / "open.far.h5")
    settings = Settings(maps_dir=maps_dir, load_demo_map=False, api_key=API_KEY, torch_threads=1)
    with serve_in_thread(settings, NearFake()) as url, httpx.Client(base_url=url, timeout=60) as client:
        listed = client.get("/maps", headers={"X-API-Key": API_KEY}).json()
        ids = [m["id"] for m in listed["data"]]
        assert ids == ["open"]  # the companion is not a map of its own
        png = encode_navtech_png_bytes(far_scan(2, keyframe_time(2) + 5))
        r = client.post("/localize", data={"map_id": "open"}, files={"scan": ("q.png", png, "image/png")},
                        headers={"X-API-Key": API_KEY})
        assert r.status_code == 200, r.text
        res = r.json()
        assert res["status"] == "localized" and res["view"] == "far" and res["keyframe"]["keyframe_id"] == 2
        assert "far_extract_ms" in res["timings_ms"]
        # by scan_id: the far features were computed at upload, as this server has a far-view map
        up = client.post("/scans", files={"scan": ("q.png", png, "image/png")}, headers={"X-API-Key": API_KEY})
        assert up.status_code == 201, up.text
        assert "far_extract_ms" in up.json()["timings_ms"]
        r = client.post("/localize", json={"map_id": "open", "scan_id": up.json()["scan_id"]},
                        headers={"X-API-Key": API_KEY})
        assert r.status_code == 200, r.text
        by_id = r.json()
        assert by_id["view"] == "far" and by_id["status"] == "localized" and by_id["keyframe"]["keyframe_id"] == 2
        assert client.delete("/maps/open", headers={"X-API-Key": API_KEY}).status_code in (200, 204)
        # with no far-view map left, an upload computes no far features (and a request by it answers near)
        up = client.post("/scans", files={"scan": ("q.png", png, "image/png")}, headers={"X-API-Key": API_KEY})
        assert up.status_code == 201 and "far_extract_ms" not in up.json()["timings_ms"]
    assert not (maps_dir / "open.h5").exists() and not (maps_dir / "open.far.h5").exists()


def test_without_a_far_view_setting_the_companion_is_ignored(far_map: Path, tmp_path: Path) -> None:
    maps_dir = tmp_path / "maps"
    maps_dir.mkdir()
    shutil.copy(far_map, maps_dir / "open.h5")
    shutil.copy(far_view_path(far_map), maps_dir / "open.far.h5")
    registry = MapRegistry(Settings(maps_dir=maps_dir, load_demo_map=False, far_view=False), NearFake())
    try:
        registry.load_all()
        assert registry.ready("open").far is None
    finally:
        registry.close()
    registry = MapRegistry(Settings(maps_dir=maps_dir, load_demo_map=False), NearFake())
    try:
        registry.load_all()
        assert registry.ready("open").far is not None
    finally:
        registry.close()


def test_a_copy_of_the_map_as_its_companion_is_not_served(far_map: Path, tmp_path: Path,
                                                           caplog: pytest.LogCaptureFixture) -> None:
    """The far view has the map's weights, so the weights hash passed a copy of the map itself as its companion
    (the same keyframes): the image it was described on tells them apart."""
    maps_dir = tmp_path / "maps"
    maps_dir.mkdir()
    shutil.copy(far_map, maps_dir / "open.h5")
    shutil.copy(far_map, maps_dir / "open.far.h5")
    registry = MapRegistry(Settings(maps_dir=maps_dir, load_demo_map=False), NearFake())
    try:
        with caplog.at_level("WARNING"):
            registry.load_all()
        assert registry.ready("open").far is None
        assert any("far view not served" in r.getMessage() and "257 px at 1.28 m/px" in r.getMessage()
                   for r in caplog.records)
    finally:
        registry.close()


def test_a_damaged_companion_leaves_the_map_served(far_map: Path, tmp_path: Path,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    maps_dir = tmp_path / "maps"
    maps_dir.mkdir()
    shutil.copy(far_map, maps_dir / "open.h5")
    (maps_dir / "open.far.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + b"\x00" * 4000)  # an HDF5 signature, then nothing
    registry = MapRegistry(Settings(maps_dir=maps_dir, load_demo_map=False), NearFake())
    try:
        with caplog.at_level("WARNING"):
            registry.load_all()
        db = registry.ready("open")
        assert db.far is None and len(db) == len(keyframe_poses())
        assert any("far view not served" in r.getMessage() for r in caplog.records)
    finally:
        registry.close()


# ---- maps registered through POST /maps: built with the companion (archive + far_view) or sent with it ----------

AUTH = {"X-API-Key": API_KEY}
N_SCANS = len(keyframe_poses())


@contextmanager
def far_app(maps_dir: Path, **settings: object) -> Iterator[TestClient]:
    """A ``TestClient`` of the app started over ``maps_dir`` with ``NearFake`` (a model with a far view)."""
    cfg = Settings(maps_dir=maps_dir, load_demo_map=False, api_key=SecretStr(API_KEY), torch_threads=1,
                   **settings)  # type: ignore[arg-type]
    with TestClient(create_app(cfg, NearFake())) as client:
        yield client


def _registry(client: TestClient) -> MapRegistry:
    return client.app.state.reradar.registry  # type: ignore[attr-defined, no-any-return]


def _far_archive() -> dict[str, tuple[str, bytes]]:
    """``POST /maps`` files: the open-land scans of ``far_map`` as a zip of PNGs, and their poses (t_s,x,y,yaw)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for i in range(N_SCANS):
            zf.writestr(f"{keyframe_time(i)}.png", encode_navtech_png_bytes(far_scan(i, keyframe_time(i))))
    poses = keyframe_poses()
    lines = ["t_s,x,y,yaw"] + [f"{keyframe_time(i) / 1e6:.6f}," + ",".join(repr(float(v)) for v in poses[i])
                               for i in range(N_SCANS)]
    return {"archive": ("scans.zip", buf.getvalue()), "poses": ("poses.csv", ("\n".join(lines) + "\n").encode())}


def _wait_built(client: TestClient, map_id: str, timeout_s: float = 120.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while (info := client.get(f"/maps/{map_id}").json())["state"] == "building" and time.monotonic() < deadline:
        time.sleep(0.05)
    return info


def _localize_far_scan(client: TestClient, map_id: str) -> dict:
    png = encode_navtech_png_bytes(far_scan(2, keyframe_time(2) + 5))
    r = client.post("/localize", data={"map_id": map_id}, files={"scan": ("q.png", png, "image/png")}, headers=AUTH)
    assert r.status_code == 200, r.text
    return r.json()


def _left_in(maps_dir: Path, map_id: str) -> list[str]:
    """Files of ``map_id`` (map, companion, verification records) and anything staged, left in ``maps_dir``."""
    return sorted(str(p.relative_to(maps_dir)) for p in maps_dir.rglob("*")
                  if p.is_file() and (p.name.startswith(f"{map_id}.") or ".staging" in p.parts))


def test_an_archive_built_with_far_view_is_served_with_its_companion(tmp_path: Path) -> None:
    maps_dir = tmp_path / "maps"
    with far_app(maps_dir) as client:
        r = client.post("/maps", data={"map_id": "moor", "preset": "boreas", "far_view": "true"},
                        files=_far_archive(), headers=AUTH)
        assert r.status_code == 202, r.text
        assert r.json()["far_view"] is True and r.json()["scans_total"] == 2 * N_SCANS  # both views' descriptions
        info = _wait_built(client, "moor")
        assert info["state"] == "ready", info
        assert info["far_view"] is True and info["num_keyframes"] == N_SCANS and info["progress"] == 1.0
        assert [(m["id"], m["far_view"]) for m in client.get("/maps").json()["data"]] == [("moor", True)]
        registry = _registry(client)
        assert registry.serves_far_view("moor")
        # the companion the CLI's `build-map --far-view` writes: the same keyframes, in the far view
        assert (maps_dir / "moor.far.h5").is_file() and not list((maps_dir / ".staging").iterdir())
        with open_map(maps_dir / "moor.far.h5", "fake-extractor-in257", "f" * 64) as far_kf:
            assert far_kf.metadata.cartesian_width_px == 257 and len(far_kf) == N_SCANS
            np.testing.assert_array_equal(far_kf.poses, registry.ready("moor").map.poses)
        res = _localize_far_scan(client, "moor")  # open land: nothing within the map's own 64 m
        assert res["view"] == "far" and res["status"] == "localized" and res["keyframe"]["keyframe_id"] == 2
        # without far_view the same archive builds the map alone
        r = client.post("/maps", data={"map_id": "near", "preset": "boreas"}, files=_far_archive(), headers=AUTH)
        assert r.status_code == 202 and r.json()["far_view"] is False and r.json()["scans_total"] == N_SCANS
        assert _wait_built(client, "near")["far_view"] is False and not (maps_dir / "near.far.h5").exists()
        assert _localize_far_scan(client, "near")["view"] == "near"
        # deleted with its map (and its verification record)
        assert client.delete("/maps/moor", headers=AUTH).status_code == 200
        assert not registry.serves_far_view("moor") and _left_in(maps_dir, "moor") == []
    with far_app(maps_dir) as client:  # nothing of it comes back at the next start
        assert [m["id"] for m in client.get("/maps").json()["data"]] == ["near"]


def test_a_map_file_registers_with_its_far_map_file(far_map: Path, tmp_path: Path) -> None:
    maps_dir = tmp_path / "maps"
    with far_app(maps_dir) as client:
        with far_map.open("rb") as fm, far_view_path(far_map).open("rb") as ff:
            r = client.post("/maps", data={"map_id": "open"}, headers=AUTH,
                            files={"map_file": ("open.h5", fm), "far_map_file": ("open.far.h5", ff)})
        assert r.status_code == 201, r.text
        assert r.json()["far_view"] is True and r.json()["state"] == "ready"
        assert _registry(client).serves_far_view("open") and (maps_dir / "open.far.h5").is_file()
        assert client.get("/maps/open").json()["far_view"] is True
        res = _localize_far_scan(client, "open")
        assert res["view"] == "far" and res["status"] == "localized" and res["keyframe"]["keyframe_id"] == 2
        # the same map without its companion: served alone
        r = upload_map_file(client, far_map, "plain")
        assert r.status_code == 201 and r.json()["far_view"] is False
        assert client.delete("/maps/open", headers=AUTH).status_code == 200
        assert _left_in(maps_dir, "open") == []


def test_a_folder_under_the_companions_name_is_a_409_that_says_what_to_do(far_map: Path, tmp_path: Path) -> None:
    """A folder named ``<id>.far.h5`` in the maps folder (made by hand) cannot be replaced by the uploaded companion:
    a 409 naming it, nothing registered, the folder kept (was a 500)."""
    maps_dir = tmp_path / "maps"
    with far_app(maps_dir) as client:
        (maps_dir / "open.far.h5").mkdir()
        with far_map.open("rb") as fm, far_view_path(far_map).open("rb") as ff:
            r = client.post("/maps", data={"map_id": "open"}, headers=AUTH,
                            files={"map_file": ("open.h5", fm), "far_map_file": ("open.far.h5", ff)})
        assert r.status_code == 409, r.text
        detail = r.json()["detail"]
        assert "a folder named open.far.h5" in detail and "remove it" in detail and str(tmp_path) not in detail
        assert client.get("/maps/open").status_code == 404
        assert not (maps_dir / "open.h5").exists() and (maps_dir / "open.far.h5").is_dir()


@pytest.fixture(scope="module")
def other_far_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A far-view map of other scans (times 1 us later) over the same poses: the companion of another map."""
    return build_map(tmp_path_factory.mktemp("other") / "other.h5", FarFake(),
                     lambda i: far_scan(i, keyframe_time(i) + 1), keyframe_poses(), radar_preset="boreas")


@pytest.mark.parametrize("case", ["another_maps_companion", "fewer_keyframes", "the_map_itself"])
def test_a_far_map_file_that_does_not_fit_the_map_is_422_and_nothing_is_registered(
        far_map: Path, other_far_map: Path, tmp_path: Path, case: str) -> None:
    maps_dir = tmp_path / "maps"
    if case == "fewer_keyframes":
        far = build_map(tmp_path / "few.h5", FarFake(), lambda i: far_scan(i, keyframe_time(i)),
                        keyframe_poses()[:4], radar_preset="boreas")
    else:
        far = {"another_maps_companion": other_far_map, "the_map_itself": far_map}[case]
    expect = {"another_maps_companion": "the time of 6 of its 6 keyframes differs",
              "fewer_keyframes": "it holds 4 keyframes, the map 6",
              "the_map_itself": "257 px at 1.28 m/px"}[case]
    with far_app(maps_dir) as client:
        with far_map.open("rb") as fm, far.open("rb") as ff:
            r = client.post("/maps", data={"map_id": "open"}, headers=AUTH,
                            files={"map_file": ("open.h5", fm), "far_map_file": ("open.far.h5", ff)})
        assert r.status_code == 422, r.text
        detail = r.json()["detail"]
        assert expect in detail and "far_map_file" in detail and str(tmp_path) not in detail, detail
        assert "build-map --far-view" in detail
        assert client.get("/maps/open").status_code == 404 and client.get("/maps").json()["count"] == 0
        assert _left_in(maps_dir, "open") == []
        # the id is free again: the map alone registers
        assert upload_map_file(client, far_map, "open").status_code == 201


def test_a_far_view_companion_sent_as_the_map_is_refused(far_map: Path, tmp_path: Path) -> None:
    with far_app(tmp_path / "maps") as client:
        r = upload_map_file(client, far_view_path(far_map), "comp")
        assert r.status_code == 422, r.text
        assert "far-view companion" in r.json()["detail"] and "'far_map_file'" in r.json()["detail"]
        assert client.get("/maps/comp").status_code == 404


def test_far_view_requests_where_the_service_serves_none_are_400(far_map: Path, tmp_path: Path) -> None:
    maps_dir = tmp_path / "maps"
    with far_app(maps_dir, far_view=False) as client:
        r = client.post("/maps", data={"map_id": "moor", "preset": "boreas", "far_view": "true"},
                        files=_far_archive(), headers=AUTH)
        assert r.status_code == 400, r.text
        assert "RERADAR_FAR_VIEW=false" in r.json()["detail"] and "'far_view'" in r.json()["detail"]
        with far_map.open("rb") as fm, far_view_path(far_map).open("rb") as ff:
            r = client.post("/maps", data={"map_id": "open"}, headers=AUTH,
                            files={"map_file": ("open.h5", fm), "far_map_file": ("open.far.h5", ff)})
        assert r.status_code == 400, r.text
        assert "RERADAR_FAR_VIEW=false" in r.json()["detail"] and "'far_map_file'" in r.json()["detail"]
        assert client.get("/maps").json()["count"] == 0
        assert _left_in(maps_dir, "moor") == [] and _left_in(maps_dir, "open") == []
        # far_view=false is the default, and allowed
        r = client.post("/maps", data={"map_id": "moor", "preset": "boreas", "far_view": "false"},
                        files=_far_archive(), headers=AUTH)
        assert r.status_code == 202 and _wait_built(client, "moor")["far_view"] is False
    with started_app(tmp_path / "fake") as client:  # a model without a far view
        r = client.post("/maps", data={"map_id": "moor", "preset": "boreas", "far_view": "true"},
                        files=_far_archive(), headers=AUTH)
        assert r.status_code == 400 and "cannot describe the far view" in r.json()["detail"], r.text


def test_far_view_fields_go_with_their_kind_of_upload(far_map: Path, tmp_path: Path) -> None:
    with far_app(tmp_path / "maps") as client:
        with far_map.open("rb") as fm:
            r = client.post("/maps", data={"map_id": "open", "far_view": "true"}, headers=AUTH,
                            files={"map_file": ("open.h5", fm)})
        assert r.status_code == 400 and "'far_map_file'" in r.json()["detail"], r.text
        with far_view_path(far_map).open("rb") as ff:
            r = client.post("/maps", data={"map_id": "moor", "preset": "boreas"}, headers=AUTH,
                            files={**_far_archive(), "far_map_file": ("open.far.h5", ff)})
        assert r.status_code == 400 and "'far_view=true'" in r.json()["detail"], r.text
        r = client.post("/maps", data={"map_id": "open"}, headers=AUTH,
                        files={"map_file": ("open.h5", far_map.read_bytes()), "far_map_file": ("f.h5", b"")})
        assert r.status_code == 400 and "empty" in r.json()["detail"], r.text
        assert client.get("/maps").json()["count"] == 0


def test_the_client_registers_maps_with_their_far_view(far_map: Path, tmp_path: Path) -> None:
    from service.client import ReRadarAPIError, ReRadarClient

    files = _far_archive()
    (tmp_path / "scans.zip").write_bytes(files["archive"][1])
    (tmp_path / "poses.csv").write_bytes(files["poses"][1])
    settings = Settings(maps_dir=tmp_path / "maps", load_demo_map=False, api_key=API_KEY, torch_threads=1)
    with serve_in_thread(settings, NearFake()) as url, ReRadarClient(url, api_key=API_KEY) as client:
        info = client.register_map("open", far_map, far_map_path=far_view_path(far_map))
        assert info.state == "ready" and info.far_view
        assert not client.register_map("plain", far_map).far_view
        with pytest.raises(ReRadarAPIError) as refused:  # another map's keyframes: nothing registered
            client.register_map("bad", far_map, far_map_path=far_map)
        assert refused.value.status_code == 422 and "far_map_file" in refused.value.detail
        assert client.register_map_from_scans("moor", tmp_path / "scans.zip", tmp_path / "poses.csv", preset="boreas",
                                              far_view=True).far_view
        built = client.wait_for_map("moor", timeout_s=120)
        assert built.far_view and built.num_keyframes == N_SCANS
        assert sorted(m.id for m in client.list_maps().data) == ["moor", "open", "plain"]


def test_what_the_folder_holds_under_a_companions_name_is_logged(far_map: Path, tmp_path: Path,
                                                                 caplog: pytest.LogCaptureFixture) -> None:
    """QA session 34: a companion without its map, a folder under a companion's name were skipped without a word,
    an attached one was not logged either, and a companion of another map had its shared arrays file written
    before its keyframes were compared."""
    maps_dir = tmp_path / "maps"
    maps_dir.mkdir()
    shutil.copy(far_map, maps_dir / "open.h5")
    shutil.copy(far_view_path(far_map), maps_dir / "open.far.h5")
    shutil.copy(far_view_path(far_map), maps_dir / "lone.far.h5")  # its map is not there
    shutil.copy(far_map, maps_dir / "other.h5")
    (maps_dir / "other.far.h5").mkdir()  # a folder under the companion's name
    other = build_map(tmp_path / "x.h5", FarFake(), lambda i: far_scan(i, keyframe_time(i) + 1), keyframe_poses(),
                      radar_preset="boreas")
    shutil.copy(far_map, maps_dir / "third.h5")
    shutil.copy(other, maps_dir / "third.far.h5")  # another map's companion: other scan times
    shutil.copy(far_map, maps_dir / "route.hdf5")  # QA session 40: skipped without a word
    registry = MapRegistry(Settings(maps_dir=maps_dir, load_demo_map=False), NearFake())
    try:
        with caplog.at_level("INFO"):
            registry.load_all()
        log = [r.getMessage() for r in caplog.records]
        assert "ignoring route.hdf5: the service serves <map_id>.h5 files; rename it to route.h5 to serve it" in log
        assert registry.ready("open").far is not None
        assert any(m.startswith("open.far.h5: far view served with map open") for m in log)
        assert any(m.startswith("lone.far.h5: far-view companion without its map lone.h5") for m in log)
        assert any(m.startswith("other.far.h5: far view not served: not a readable file") for m in log)
        assert any(m.startswith("third.far.h5: far view not served") and "does not hold the keyframes" in m
                   for m in log)
        assert registry.ready("other").far is None and registry.ready("third").far is None
        arrays = registry.settings.arrays_dir
        assert arrays is not None  # shared arrays are on by default
        served = [registry.ready(m) for m in ("open", "other", "third")]
        used = {d.arrays.path.name for db in served for d in (db, db.far) if d is not None and d.arrays is not None}
        assert len(used) >= 2  # the maps' and the served companion's
        assert {p.name for p in arrays.iterdir() if p.is_file() and not p.name.endswith(".lock")} == used
    finally:
        registry.close()


# ---- session 34's review: two writers of one id, companions without their map, notes and logs --------------------

def _writer(root: Path, who: str) -> tuple[Path, Path]:
    """Writer ``who``'s staged map and companion (their bytes name the writer), in a folder of its own."""
    staged = root / f"staging-{who}"
    staged.mkdir()
    (staged / "m.h5").write_bytes(f"map of {who}".encode())
    (staged / "m.far.h5").write_bytes(f"companion of {who}".encode())
    return staged / "m.h5", staged / "m.far.h5"


@pytest.mark.parametrize("b_runs", ["inside_a_until_its_commit", "whole_before_a_commits"])
def test_of_two_writers_of_one_id_the_installed_map_has_its_own_companion(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, b_runs: str) -> None:
    """Session 34's review: with Redis down two replicas registering one id at the same moment could leave the
    winner's map without its companion (B replaced A's, A's map won, B took its own back). The interleaving is forced
    here: A's map commit runs writer B's whole install first, and ``inside_a_until_its_commit`` makes A's commit land
    just before B's own."""
    import service.core.registry as registry_module

    maps_dir = tmp_path / "maps"
    maps_dir.mkdir()
    target = maps_dir / "m.h5"
    a_map, a_far = _writer(tmp_path, "A")
    b_map, b_far = _writer(tmp_path, "B")
    real_install = registry_module.install_file
    b_outcome: list[str] = []
    a_committed: list[bool] = []

    def install(src: Path, dst: Path, exclusive: bool = False) -> Path:
        if Path(src) == a_map:  # A's commit: B's whole install runs first
            try:
                registry_module.install_map_files(b_map, target, b_far)
                b_outcome.append("installed")
            except FileExistsError:
                b_outcome.append("refused")
            if a_committed:  # inside B's install, just before B's commit
                return Path(dst)
        if Path(src) == b_map and b_runs == "inside_a_until_its_commit":
            real_install(a_map, target, exclusive=True)  # between B's companion and B's map
            a_committed.append(True)
        return real_install(src, dst, exclusive=exclusive)

    monkeypatch.setattr(registry_module, "install_file", install)
    if b_runs == "inside_a_until_its_commit":
        registry_module.install_map_files(a_map, target, a_far)
        assert b_outcome == ["refused"]
        winner, loser = "A", (b_map, b_far)
    else:
        with pytest.raises(FileExistsError):
            registry_module.install_map_files(a_map, target, a_far)
        assert b_outcome == ["installed"]
        winner, loser = "B", (a_map, a_far)
    assert target.read_bytes() == f"map of {winner}".encode()
    assert far_view_path(target).read_bytes() == f"companion of {winner}".encode()
    assert sorted(p.name for p in maps_dir.iterdir()) == ["m.far.h5", "m.h5"]  # nothing else left in the folder
    other = "B" if winner == "A" else "A"
    assert loser[0].read_bytes() == f"map of {other}".encode()  # the loser's files stay where they were
    assert loser[1].read_bytes() == f"companion of {other}".encode()


def test_an_install_replaces_or_removes_a_companion_without_its_map_and_a_failed_one_leaves_nothing(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    from service.core.registry import install_map_files

    maps_dir = tmp_path / "maps"
    maps_dir.mkdir()
    orphan = maps_dir / "m.far.h5"
    orphan.write_bytes(b"left by a stopped install")
    a_map, a_far = _writer(tmp_path, "A")
    with caplog.at_level("WARNING"):
        install_map_files(a_map, maps_dir / "m.h5", a_far)
    assert orphan.read_bytes() == b"companion of A" and not a_map.exists() and not a_far.exists()
    assert any(r.getMessage().startswith("m.far.h5: a far-view companion that lay there without its map")
               and "is replaced by the one installed with map m" in r.getMessage() for r in caplog.records)
    # a map without a companion removes one found without its map: never served with one it did not bring
    (maps_dir / "p.far.h5").write_bytes(b"left by a stopped delete")
    p_map, _ = _writer(tmp_path, "P")
    caplog.clear()
    with caplog.at_level("WARNING"):
        install_map_files(p_map, maps_dir / "p.h5")
    assert (maps_dir / "p.h5").read_bytes() == b"map of P" and not (maps_dir / "p.far.h5").exists()
    assert any("is removed: map p is installed without one" in r.getMessage() for r in caplog.records)
    # a companion that cannot go under its name (a folder there): refused before anything is touched, with what to do
    (maps_dir / "q.far.h5").mkdir()
    q_map, q_far = _writer(tmp_path, "Q")
    with pytest.raises(ConflictError, match="a folder named q.far.h5 .* an operator must remove it") as refused:
        install_map_files(q_map, maps_dir / "q.h5", q_far)
    assert str(tmp_path) not in str(refused.value)
    assert not (maps_dir / "q.h5").exists() and (maps_dir / "q.far.h5").is_dir()
    assert q_map.read_bytes() == b"map of Q" and q_far.read_bytes() == b"companion of Q"
    # a map id taken: refused before anything is touched
    with pytest.raises(FileExistsError):
        install_map_files(q_map, maps_dir / "m.h5", q_far)
    assert orphan.read_bytes() == b"companion of A" and q_far.is_file()
    assert sorted(p.name for p in maps_dir.iterdir()) == ["m.far.h5", "m.h5", "p.h5", "q.far.h5"]


def test_a_commit_that_fails_takes_its_companion_back_and_leaves_anothers(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """A cancel or an error at the map's install leaves nothing of this install: its own companion, linked first,
    is taken back, while a companion it found there (another writer's, mid-install) stays."""
    import service.core.registry as registry_module

    def cancelled(src: Path, dst: Path, exclusive: bool = False) -> Path:
        raise KeyboardInterrupt

    monkeypatch.setattr(registry_module, "install_file", cancelled)
    maps_dir = tmp_path / "maps"
    maps_dir.mkdir()
    a_map, a_far = _writer(tmp_path, "A")
    with pytest.raises(KeyboardInterrupt):
        registry_module.install_map_files(a_map, maps_dir / "m.h5", a_far)
    assert list(maps_dir.iterdir()) == [] and a_map.is_file() and a_far.read_bytes() == b"companion of A"
    (maps_dir / "m.far.h5").write_bytes(b"another writer's")
    with pytest.raises(KeyboardInterrupt):
        registry_module.install_map_files(a_map, maps_dir / "m.h5", a_far)
    assert [p.name for p in maps_dir.iterdir()] == ["m.far.h5"]
    assert (maps_dir / "m.far.h5").read_bytes() == b"another writer's" and a_far.is_file()


def test_a_registration_serves_only_the_companion_it_brings(far_map: Path, other_far_map: Path, tmp_path: Path,
                                                            caplog: pytest.LogCaptureFixture) -> None:
    """Session 34's review: a companion left without its map (a process killed between the install's two steps)
    was logged at every start as a misnamed map, and a later registration of its id served it when its keyframes
    matched. At start it is now logged as what it most likely is; a registration removes it (or replaces it by the
    uploaded one, which it logs as served: that log line was missing for uploads)."""
    maps_dir = tmp_path / "maps"
    maps_dir.mkdir()
    shutil.copy(far_view_path(far_map), maps_dir / "open.far.h5")  # open's own keyframes, but no map open.h5
    shutil.copy(other_far_map, maps_dir / "moor.far.h5")
    registry = MapRegistry(Settings(maps_dir=maps_dir, load_demo_map=False), NearFake())
    try:
        with caplog.at_level("INFO"):
            registry.load_all()
        log = [r.getMessage() for r in caplog.records]
        assert any(m.startswith("open.far.h5: far-view companion without its map open.h5: not served. Most likely "
                                "left by an install or a delete of map open that was stopped midway") for m in log)
        assert (maps_dir / "open.far.h5").is_file()  # not removed at start: it may be another writer's, mid-install
        staged = registry.staging_dir() / "upload.h5"
        shutil.copy(far_map, staged)
        caplog.clear()
        with caplog.at_level("INFO"):
            entry = registry.register_file("open", staged)
        assert entry.state == "ready" and entry.db is not None and entry.db.far is None
        assert not registry.serves_far_view("open") and not (maps_dir / "open.far.h5").exists()
        assert not any("far view served" in r.getMessage() for r in caplog.records)
        # with its far_map_file: the uploaded companion replaces the other map's, and is logged as served
        staged, far_staged = registry.staging_dir() / "m.h5", registry.staging_dir() / "f.h5"
        shutil.copy(far_map, staged)
        shutil.copy(far_view_path(far_map), far_staged)
        caplog.clear()
        with caplog.at_level("INFO"):
            entry = registry.register_file("moor", staged, far_staged)
        assert entry.db is not None and entry.db.far is not None and registry.serves_far_view("moor")
        with open_map(maps_dir / "moor.far.h5", "fake-extractor-in257", "f" * 64) as far_kf:
            np.testing.assert_array_equal(far_kf.timestamps_us, entry.db.map.timestamps_us)  # open's, not other's
        log = [r.getMessage() for r in caplog.records]
        assert f"moor.far.h5: far view served with map moor ({N_SCANS} keyframes, with dense images)" in log
    finally:
        registry.close()


def test_a_far_view_build_says_what_it_does_at_half_progress(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Session 34's review: a build with ``far_view=true`` stood at progress 0.5, during the map's own
    place-repetition pass, without a ``note``. The note is read at the moment each place-repetition pass starts."""
    import maps.build
    from service.core.registry import MapEntry, last_pass_note

    def entry(done: int, total: int, far_view: bool) -> MapEntry:
        return MapEntry("m", Path("m.h5"), "building", scans_done=done, scans_total=total, far_view=far_view)

    half = last_pass_note(entry(6, 12, True))
    assert half is not None and "every scan is described in the map's own view" in half
    assert "measuring where the map repeats itself" in half and "far view" in half
    end = last_pass_note(entry(12, 12, True))
    assert end is not None and "both views" in end and "far-view companion" in end
    for e in (entry(5, 12, True), entry(7, 12, True), entry(6, 12, False)):
        assert last_pass_note(e) is None
    seen: list[tuple[float, str | None]] = []
    real_measure = maps.build.measure_place_repetition
    maps_dir = tmp_path / "maps"
    with far_app(maps_dir) as client:
        registry = _registry(client)

        def measure(*args: object, **kwargs: object) -> object:
            building = registry.get("moor")
            seen.append((building.progress, registry.build_note(building)))
            return real_measure(*args, **kwargs)  # type: ignore[arg-type]

        monkeypatch.setattr(maps.build, "measure_place_repetition", measure)
        r = client.post("/maps", data={"map_id": "moor", "preset": "boreas", "far_view": "true"},
                        files=_far_archive(), headers=AUTH)
        assert r.status_code == 202, r.text
        assert _wait_built(client, "moor")["state"] == "ready"
    assert [p for p, _ in seen] == [0.5, 1.0]  # the map's own pass, then its companion's
    assert seen[0][1] == last_pass_note(entry(N_SCANS, 2 * N_SCANS, True))
    assert seen[1][1] == last_pass_note(entry(2 * N_SCANS, 2 * N_SCANS, True))
