"""A map's far-view companion (``build-map --far-view``): built beside the map, served with it, used for the
answers the map's own view refuses, deleted with it, and never served for another map."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest

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
from service.core.registry import MapRegistry
from service.demo import serve_in_thread

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import API_KEY, FakeExtractor, keyframe_poses, keyframe_time  # noqa: E402

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


@pytest.fixture(scope="module")
def far_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("far") / "open.h5"
    return build_map(out, NearFake(), lambda i: far_scan(i, keyframe_time(i)), keyframe_poses(),
                     radar_preset="boreas", name="open", batch_size=4, far_view=FarViewConfig())


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
