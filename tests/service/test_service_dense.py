"""The far view's dense registration as served: the companion stores every keyframe's dense image, and a scan that
both views refuse is placed by whole-image correlation (``registration: dense``), inline or by ``scan_id``."""

from __future__ import annotations

import shutil
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import h5py
import httpx
import numpy as np
import pytest

from maps.database import FAR_VIEW, MapDatabase
from maps.paths import far_view_path
from maps.store import open_map
from reradar_core.errors import MapFormatError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.cartesian import CartesianConfig
from reradar_core.io.scan import RadarScan, encode_navtech_png_bytes
from reradar_core.matching.dense import dense_image, dense_image_settings
from service.core.config import Settings
from service.demo import serve_in_thread

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import API_KEY, FakeExtractor, keyframe_poses, keyframe_time  # noqa: E402
from test_service_far_view import NearFake, build_open_land_map, far_scan  # noqa: E402


class LostFarFake(FakeExtractor):
    """A far view whose landmarks never repeat between two scans (each scan's own random points, drawn from its
    time), while its global descriptor still names the place: the far view retrieves but never verifies."""

    model_id = "fake-extractor-in257"
    cartesian = CartesianConfig(257, 1.28)

    def describe(self, scan: RadarScan) -> ScanFeatures:
        f = super().describe(scan)
        rng = np.random.default_rng(int(scan.timestamp_us) % 2**32)
        xy = rng.uniform(-150, 150, size=(40, 2)).astype(np.float32)
        local = rng.normal(size=(40, f.local_descriptors.shape[1]))
        local /= np.linalg.norm(local, axis=1, keepdims=True)
        return ScanFeatures(f.global_descriptor, xy, local.astype(np.float16), f.timestamp_us)


class LostNearFake(NearFake):
    def with_view(self, cartesian: CartesianConfig) -> LostFarFake:
        assert (cartesian.width_px, cartesian.resolution_m) == (257, 1.28)
        return LostFarFake()


@pytest.fixture(scope="module")
def lost_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_open_land_map(tmp_path_factory.mktemp("dense") / "moor.h5", LostNearFake())


def _pair_in(folder: Path, lost_map: Path) -> Path:
    """A copy of the map and its companion in ``folder`` (created); returns the map's path."""
    folder.mkdir(parents=True, exist_ok=True)
    out = folder / "moor.h5"
    shutil.copy(lost_map, out)
    shutil.copy(far_view_path(lost_map), far_view_path(out))
    return out


@contextmanager
def _served(maps_dir: Path) -> Iterator[httpx.Client]:
    """The service over ``maps_dir`` with the lost-far-view fake, and a client sending the API key."""
    settings = Settings(maps_dir=maps_dir, load_demo_map=False, api_key=API_KEY, torch_threads=1)
    with serve_in_thread(settings, LostNearFake()) as url, \
            httpx.Client(base_url=url, timeout=60, headers={"X-API-Key": API_KEY}) as client:
        yield client


def test_the_companion_stores_every_keyframes_dense_image(lost_map: Path) -> None:
    with open_map(far_view_path(lost_map), "fake-extractor-in257", "f" * 64) as far, \
            open_map(lost_map, "fake-extractor", "f" * 64) as near:
        assert far.dense_settings == dense_image_settings(FAR_VIEW.dense)
        for i in (0, len(far) - 1):
            expected = dense_image(far_scan(i, keyframe_time(i)), FAR_VIEW.cartesian, FAR_VIEW.dense)
            np.testing.assert_allclose(far.read_dense_image(i), expected, atol=1e-3)  # stored float16
        assert near.dense_settings is None  # the map itself keeps none
        with pytest.raises(MapFormatError, match="no dense images"):
            near.read_dense_image(0)
        with pytest.raises(IndexError):
            far.read_dense_image(len(far))


def test_a_scan_both_views_refuse_is_placed_by_dense_registration(lost_map: Path) -> None:
    near_db = MapDatabase.open(lost_map, "fake-extractor", "f" * 64)
    far_db = MapDatabase.open(far_view_path(lost_map), "fake-extractor-in257", "f" * 64)
    try:
        near_db.attach_far(far_db)
        assert near_db.far_dense
        scan = far_scan(3, keyframe_time(3) + 7)  # keyframe 3's place, seen again
        near_q = NearFake().describe(scan)
        without = near_db.localize_views(near_q, lambda: LostFarFake().describe(scan))
        assert without.view == "far" and not without.result.localized  # no landmark repeats
        answer = near_db.localize_views(near_q, lambda: LostFarFake().describe(scan),
                                        dense_query=lambda: dense_image(scan, FAR_VIEW.cartesian, FAR_VIEW.dense))
        assert answer.registration == "dense" and answer.result.localized and answer.place_id == 3
        np.testing.assert_allclose(answer.result.T_map_query, keyframe_poses()[3], atol=0.1)
    finally:
        near_db.close()


def test_a_companion_of_other_dense_settings_is_not_correlated(lost_map: Path, tmp_path: Path) -> None:
    """Images made with another recipe would correlate wrongly: the far view answers as without them."""
    out = _pair_in(tmp_path, lost_map)
    with h5py.File(far_view_path(out), "r+") as f:
        f.attrs["dense_images"] = '{"blur_px": 2.0, "highpass_px": 4.0, "version": 1}'
    near_db = MapDatabase.open(out, "fake-extractor", "f" * 64)
    near_db.attach_far(MapDatabase.open(far_view_path(out), "fake-extractor-in257", "f" * 64))
    try:
        assert not near_db.far_dense
        scan = far_scan(3, keyframe_time(3) + 7)

        def never() -> np.ndarray:
            raise AssertionError("the query's dense image was made for a companion it cannot be compared with")

        answer = near_db.localize_views(NearFake().describe(scan), lambda: LostFarFake().describe(scan),
                                        dense_query=never)
        assert answer.registration == "landmarks" and not answer.result.localized
    finally:
        near_db.close()


def test_the_service_answers_an_inline_scan_by_dense_registration(lost_map: Path, tmp_path: Path) -> None:
    with _served(_pair_in(tmp_path / "maps", lost_map).parent) as client:
        png = encode_navtech_png_bytes(far_scan(2, keyframe_time(2) + 5))
        r = client.post("/localize", data={"map_id": "moor"}, files={"scan": ("q.png", png, "image/png")})
        assert r.status_code == 200, r.text
        res = r.json()
        assert res["status"] == "localized" and res["view"] == "far" and res["registration"] == "dense"
        assert res["keyframe"]["keyframe_id"] == 2 and res["num_inliers"] == 0
        assert res["pose_uncertainty"]["sigma_yaw_deg"] == pytest.approx(np.rad2deg(0.007), rel=1e-3)
        assert abs(res["pose"]["x_m"] - keyframe_poses()[2, 0]) < 0.5 and 0.9 <= res["confidence"] <= 1.0
        assert "dense_image_ms" in res["timings_ms"] and "dense_ms" in res["timings_ms"]
        # by scan_id: the dense image was made at upload (as this server has a companion with dense images)
        up = client.post("/scans", files={"scan": ("q.png", png, "image/png")})
        assert up.status_code == 201, up.text
        assert "dense_image_ms" in up.json()["timings_ms"]
        r = client.post("/localize", json={"map_id": "moor", "scan_id": up.json()["scan_id"]})
        assert r.status_code == 200, r.text
        by_id = r.json()
        assert by_id["status"] == "localized" and by_id["registration"] == "dense"
        assert by_id["keyframe"]["keyframe_id"] == 2 and by_id["pose"] == res["pose"]  # the same image, inline or cached


def test_a_companion_without_dense_images_makes_none_at_upload(lost_map: Path, tmp_path: Path) -> None:
    """A companion built before dense images (or sent without them): uploads skip the image, answers stay the far
    view's."""
    out = _pair_in(tmp_path / "maps", lost_map)
    with h5py.File(far_view_path(out), "r+") as f:
        del f.attrs["dense_images"]
    with _served(out.parent) as client:
        png = encode_navtech_png_bytes(far_scan(2, keyframe_time(2) + 5))
        up = client.post("/scans", files={"scan": ("q.png", png, "image/png")})
        assert up.status_code == 201 and "dense_image_ms" not in up.json()["timings_ms"]
        assert "far_extract_ms" in up.json()["timings_ms"]
        r = client.post("/localize", data={"map_id": "moor"}, files={"scan": ("q.png", png, "image/png")})
        assert r.json()["status"] == "not_localized" and r.json()["registration"] == "landmarks"
        assert "dense_image_ms" not in r.json()["timings_ms"]


def test_a_damaged_dense_image_costs_that_candidate_only(lost_map: Path, tmp_path: Path,
                                                          caplog: pytest.LogCaptureFixture) -> None:
    """A served file's damage is not the request's fault: no error answer, the candidate aligns with nothing."""
    out = _pair_in(tmp_path, lost_map)
    with h5py.File(far_view_path(out), "r+") as f:
        f["keyframes/000003/dense_image"][0, 0] = np.nan
    near_db = MapDatabase.open(out, "fake-extractor", "f" * 64)
    near_db.attach_far(MapDatabase.open(far_view_path(out), "fake-extractor-in257", "f" * 64))
    try:
        scan = far_scan(3, keyframe_time(3) + 7)
        dense_q = lambda: dense_image(scan, FAR_VIEW.cartesian, FAR_VIEW.dense)  # noqa: E731
        with caplog.at_level("WARNING", logger="maps.database"):
            answer = near_db.localize_views(NearFake().describe(scan), lambda: LostFarFake().describe(scan),
                                            dense_query=dense_q)
        assert not (answer.result.localized and answer.place_id == 3)
        assert any("dense image of keyframe 3 unreadable" in r.getMessage() for r in caplog.records)
        # the others are still read: keyframe 2's place is placed as before
        scan2 = far_scan(2, keyframe_time(2) + 7)
        answer = near_db.localize_views(NearFake().describe(scan2), lambda: LostFarFake().describe(scan2),
                                        dense_query=lambda: dense_image(scan2, FAR_VIEW.cartesian, FAR_VIEW.dense))
        assert answer.registration == "dense" and answer.place_id == 2
    finally:
        near_db.close()


def test_map_info_says_whether_a_companion_holds_dense_images(lost_map: Path) -> None:
    import json

    from typer.testing import CliRunner

    from reradar_cli import app

    far = json.loads(CliRunner().invoke(app, ["map-info", str(far_view_path(lost_map))]).stdout)
    assert far["dense_images"]["default_settings"] is True
    assert json.loads(far["dense_images"]["settings"]) == json.loads(dense_image_settings(FAR_VIEW.dense))
    assert json.loads(CliRunner().invoke(app, ["map-info", str(lost_map)]).stdout)["dense_images"] is None


@pytest.mark.parametrize("bad", [np.int64(3), "x" * 20_000])
def test_a_malformed_dense_images_attribute_costs_the_dense_step_only(lost_map: Path, tmp_path: Path, bad: object,
                                                                      caplog: pytest.LogCaptureFixture) -> None:
    """The images are an optional extra (QA session 39: such an attribute stopped the whole far view being served)."""
    far = far_view_path(_pair_in(tmp_path, lost_map))
    with h5py.File(far, "r+") as f:
        f.attrs["dense_images"] = bad
    with caplog.at_level("WARNING", logger="maps.store"), open_map(far, "fake-extractor-in257", "f" * 64) as kf:
        assert kf.dense_settings is None and len(kf) == len(keyframe_poses())
        assert kf.read_keyframe(0).keypoints_xy_m.shape[1] == 2
    assert "its dense images are not used" in caplog.text


def test_a_companion_that_declares_dense_images_it_does_not_hold_is_served_without_the_step(
        lost_map: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """QA session 39: such a companion was logged "with dense images" and every refused sparse query correlated
    against all-zero images (and every upload made an image for nothing)."""
    out = _pair_in(tmp_path, lost_map)
    with h5py.File(far_view_path(out), "r+") as f:
        for name in f["keyframes"]:
            del f["keyframes"][name]["dense_image"]
    near_db = MapDatabase.open(out, "fake-extractor", "f" * 64)
    with caplog.at_level("WARNING", logger="maps.database"):
        near_db.attach_far(MapDatabase.open(far_view_path(out), "fake-extractor-in257", "f" * 64))
    try:
        assert not near_db.far_dense and "declares dense images but keyframe 0's is unreadable" in caplog.text
    finally:
        near_db.close()


def test_a_stored_scan_entry_is_read_only_within_bounds() -> None:
    """QA session 39 (fleet mode): a dense image of another width, one that overflows float16, a small entry
    declaring a huge array: dropped or unreadable, never a 500 or a huge allocation."""
    import io

    from service.core.shared_state import decode_features, encode_features

    f = FakeExtractor().describe(far_scan(1, keyframe_time(1)))
    base = encode_features(f, "boreas")
    with np.load(io.BytesIO(base), allow_pickle=False) as z:
        fields = {k: z[k] for k in z.files}

    def blob(**extra: np.ndarray) -> bytes:
        buf = io.BytesIO()
        np.savez(buf, **{**fields, **extra})
        return buf.getvalue()

    for bad in (np.zeros((64, 64), np.float32), np.zeros((512, 512), np.float32), np.full((257, 257), 1e6)):
        assert decode_features(blob(dense_image=bad))[4] is None
    ok = decode_features(blob(dense_image=np.full((257, 257), 0.01, np.float32)))[4]
    assert ok is not None and ok.dtype == np.float16
    # a header declaring 200,000 x 200,000 float32 (160 GB) in a few bytes: refused before anything is read
    huge = io.BytesIO()
    with __import__("zipfile").ZipFile(huge, "w") as zf:
        for k, v in fields.items():
            with zf.open(f"{k}.npy", "w") as fh:
                np.lib.format.write_array(fh, v)
        with zf.open("dense_image.npy", "w") as fh:
            np.lib.format.write_array_header_1_0(fh, {"descr": "<f4", "fortran_order": False, "shape": (200000, 200000)})
    with pytest.raises(ValueError, match="declares"):
        decode_features(huge.getvalue())
