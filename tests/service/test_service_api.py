"""The HTTP API over a real uvicorn server on localhost, driven with httpx (fake extractor: fast, exact)."""

from __future__ import annotations

import io
import math
import sys
import time
import zipfile
from pathlib import Path

import h5py
import httpx
import numpy as np
import pytest

from reradar_core.geometry.se2 import wrap_angle
from reradar_core.io.poses import PoseSequence, write_txyyaw_csv
from reradar_core.io.presets import get_preset, mid_sweep_times_us
from reradar_core.io.scan import encode_navtech_png_bytes
from service.client import ReRadarAPIError, ReRadarClient

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import (  # noqa: E402
    API_KEY,
    N_KEYFRAMES,
    keyframe_poses,
    keyframe_time,
    make_scan,
    register_map_file,
)

AUTH = {"X-API-Key": API_KEY}


@pytest.fixture(scope="module")
def client(server: tuple[str, Path], fake_map: Path) -> httpx.Client:
    """httpx client on the live server, with the fake map registered as ``route-a`` through POST /maps."""
    url, _ = server
    with httpx.Client(base_url=url, timeout=60) as c:
        register_map_file(c, fake_map, "route-a")
        yield c


def _png(seed: int, t_us: int, roll: int = 0) -> bytes:
    scan = make_scan(seed, t_us)
    if roll:
        scan = scan.with_power(np.roll(scan.power, roll, axis=0))
    return encode_navtech_png_bytes(scan)


def test_a_map_with_first_azimuth_poses_says_so(client: httpx.Client, fake_map: Path, tmp_path: Path) -> None:
    """QA (session 24): a map written before pose_time existed is served with first-azimuth poses, and only the
    server log said so; its map info now names the instant its poses (and answers) refer to."""
    old = tmp_path / "old.h5"
    old.write_bytes(fake_map.read_bytes())
    with h5py.File(old, "r+") as f:
        del f.attrs["pose_time"]
        del f["place_repetition"]  # nor did it store its place repetition (session 28)
    register_map_file(client, old, "route-old")
    info = client.get("/maps/route-old").json()
    assert info["pose_time"] == "first_azimuth" and info["place_repetition"] == "not_stored"
    assert client.delete("/maps/route-old", headers=AUTH).status_code in (200, 204)


def test_health_ready_metrics(client: httpx.Client) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz").json()
    assert ready["status"] == "ready" and ready["model_id"] == "fake-extractor" and ready["maps_ready"] >= 1
    client.get("/maps")
    text = client.get("/metrics").text
    assert 'reradar_http_requests_total{method="GET",route="/maps",status="200"}' in text
    assert "reradar_http_request_duration_seconds_bucket" in text
    assert "reradar_maps_loaded" in text


def test_map_listing_and_registration_rules(client: httpx.Client, fake_map: Path, server: tuple[str, Path]) -> None:
    body = client.get("/maps").json()
    assert body["count"] == len(body["data"]) >= 1
    info = next(m for m in body["data"] if m["id"] == "route-a")
    assert info["state"] == "ready" and info["num_keyframes"] == N_KEYFRAMES and info["index_kind"] == "flat"
    assert client.get("/maps/route-a").json()["model_id"] == "fake-extractor"
    assert info["pose_time"] == "mid_sweep"
    assert info["place_repetition"] == "stored"  # built by build_map under the service's (default) settings
    with fake_map.open("rb") as fh:
        files = {"map_file": ("fake.h5", fh.read())}
    assert client.post("/maps", data={"map_id": "route-a"}, files=files, headers=AUTH).status_code == 409
    assert client.post("/maps", data={"map_id": "route-b"}, files=files).status_code == 401
    assert client.post("/maps", data={"map_id": "route-b"}, files=files,
                       headers={"X-API-Key": "wrong"}).status_code == 401
    for bad in ("../escape", "A", "a.b", "x" * 65, "", "..", "/abs"):
        r = client.post("/maps", data={"map_id": bad}, files=files, headers=AUTH)
        assert r.status_code == 422, (bad, r.status_code)
    assert sorted(p.name for p in server[1].glob("*.h5")) == ["route-a.h5"]


def test_bad_map_uploads_are_refused_without_damage(client: httpx.Client, server: tuple[str, Path],
                                                    fake_map: Path, tmp_path: Path) -> None:
    maps_dir = server[1]
    before = (maps_dir / "route-a.h5").read_bytes()
    r = client.post("/maps", data={"map_id": "junk"}, files={"map_file": ("m.h5", b"garbage" * 100)}, headers=AUTH)
    assert r.status_code == 422 and "HDF5" in r.json()["detail"]
    assert client.post("/maps", data={"map_id": "junk"}, files={"map_file": ("m.h5", b"")},
                       headers=AUTH).status_code == 400
    other = tmp_path / "other.h5"
    other.write_bytes(fake_map.read_bytes())
    with h5py.File(other, "r+") as f:
        f.attrs["weights_sha256"] = "0" * 64
    r = client.post("/maps", data={"map_id": "other"}, files={"map_file": ("o.h5", other.read_bytes())}, headers=AUTH)
    assert r.status_code == 409 and r.json()["error"] == "model_mismatch"
    r = client.post("/maps", data={"map_id": "big"}, files={"map_file": ("b.h5", b"0" * (9 * 2**20))}, headers=AUTH)
    assert r.status_code == 413
    r = client.post("/maps", data={"map_id": "both"}, headers=AUTH)
    assert r.status_code == 400
    assert sorted(p.name for p in maps_dir.glob("*.h5")) == ["route-a.h5"]
    assert (maps_dir / "route-a.h5").read_bytes() == before
    assert not any((maps_dir / ".staging").glob("*")) if (maps_dir / ".staging").exists() else True
    assert client.get("/maps/junk").status_code == 404


def test_upload_retrieve_localize_by_reference(client: httpx.Client) -> None:
    r = client.post("/scans", files={"scan": ("q.png", _png(3, 123), "image/png")})
    assert r.status_code == 201, r.text
    scan = r.json()
    assert scan["num_keypoints"] == 40 and scan["preset"] == "boreas" and scan["timestamp_us"] == 123
    r = client.post("/maps/route-a/retrieve", json={"scan_id": scan["scan_id"], "top_k": 3})
    assert r.status_code == 200, r.text
    kfs = r.json()["keyframes"]
    assert len(kfs) == 3 and kfs[0]["keyframe_id"] == 3 and kfs[0]["descriptor_distance"] < 1e-3
    assert kfs[0]["timestamp_us"] == keyframe_time(3)
    r = client.post("/localize", json={"map_id": "route-a", "scan_id": scan["scan_id"]})
    assert r.status_code == 200, r.text
    res = r.json()
    assert res["status"] == "localized" and res["reason"] is None
    pose = keyframe_poses()[3]
    assert res["pose"]["x_m"] == pytest.approx(pose[0], abs=0.05)
    assert res["pose"]["y_m"] == pytest.approx(pose[1], abs=0.05)
    assert res["pose"]["yaw_deg"] == pytest.approx(math.degrees(pose[2]), abs=0.1)
    assert res["keyframe"]["keyframe_id"] == 3 and res["num_inliers"] == 40 and res["inlier_ratio"] == 1.0
    assert {"retrieve_ms", "verify_ms", "total_ms"} <= set(res["timings_ms"])


def test_inline_localize_recovers_rotation(client: httpx.Client) -> None:
    # rolling the polar image by +s azimuth rows = the vehicle turned counter-clockwise by s * 360/400 degrees
    s = 25
    files = {"scan": ("q.png", _png(4, 5, roll=s), "image/png")}
    r = client.post("/localize", data={"map_id": "route-a"}, files=files)
    assert r.status_code == 200, r.text
    res = r.json()
    assert res["status"] == "localized" and res["keyframe"]["keyframe_id"] == 4
    assert res["relative_pose"]["yaw_deg"] == pytest.approx(s * 360 / 400, abs=0.5)
    assert math.hypot(res["relative_pose"]["x_m"], res["relative_pose"]["y_m"]) < 0.5
    expected_yaw = math.degrees(float(wrap_angle(keyframe_poses()[4, 2] + math.radians(s * 0.9))))
    assert res["pose"]["yaw_deg"] == pytest.approx(expected_yaw, abs=0.5)
    assert "decode_ms" in res["timings_ms"] and "extract_ms" in res["timings_ms"]
    # how precise the pose is: a symmetric 3 x 3 covariance (x m, y m, yaw deg) whose diagonal the sigmas are, and
    # small enough that the pose's actual error (within 0.5 m / deg above) is not many sigmas off
    unc = res["pose_uncertainty"]
    cov = np.array(unc["covariance"])
    assert cov.shape == (3, 3) and np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
    np.testing.assert_allclose([unc["sigma_x_m"], unc["sigma_y_m"], unc["sigma_yaw_deg"]], np.sqrt(np.diag(cov)))
    assert 0.0 < unc["sigma_x_m"] < 2.0 and 0.0 < unc["sigma_y_m"] < 2.0 and 0.0 < unc["sigma_yaw_deg"] < 2.0
    # the test map's keyframes carry no drive in time (no keyframe motion): the rigid registration's pose
    assert "covariance_ms" in res["timings_ms"] and res["motion_compensated"] is False


def test_navtech_npy_transport_gives_the_pngs_answer(client: httpx.Client) -> None:
    """An .npy of the PNG's pixels sent with scan_layout=navtech is the same scan: the same answer, also by
    reference (POST /scans) and through the Python client; other layouts and bad values are refused."""
    import io

    import cv2

    png = _png(4, 5, roll=25)
    buf = io.BytesIO()
    np.save(buf, cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED))
    raw = buf.getvalue()

    def answer(r: httpx.Response) -> tuple:
        assert r.status_code == 200, r.text
        j = r.json()
        return j["status"], j["keyframe"]["keyframe_id"], j["pose"], j["num_inliers"], j["confidence"]

    want = answer(client.post("/localize", data={"map_id": "route-a"}, files={"scan": ("q.png", png)}))
    got = answer(client.post("/localize", data={"map_id": "route-a", "scan_layout": "navtech"},
                             files={"scan": ("q.npy", raw)}))
    assert got == want and want[0] == "localized"
    up = client.post("/scans", data={"scan_layout": "navtech"}, files={"scan": ("q.npy", raw)})
    assert up.status_code == 201, up.text
    assert answer(client.post("/localize", json={"map_id": "route-a", "scan_id": up.json()["scan_id"]})) == want
    via = ReRadarClient(str(client.base_url)).localize("route-a", scan_bytes=raw, filename="q.npy",
                                                       scan_layout="navtech")
    assert (via.status, via.keyframe.keyframe_id if via.keyframe else None) == want[:2]
    # the same array read as a polar .npy (the default) is another scan: the metadata columns become range bins,
    # 11 more than the map's preset has, so it is refused (a polar .npy takes the map's geometry)
    polar = client.post("/localize", data={"map_id": "route-a"}, files={"scan": ("q.npy", raw)})
    assert polar.status_code == 422 and "range bins" in polar.json()["detail"]
    bad = client.post("/localize", data={"map_id": "route-a", "scan_layout": "raw"}, files={"scan": ("q.npy", raw)})
    assert bad.status_code == 400 and "scan_layout" in bad.json()["detail"]
    floats = io.BytesIO()
    np.save(floats, np.zeros((100, 11 + 200), np.float32))
    r = client.post("/localize", data={"map_id": "route-a", "scan_layout": "navtech"},
                    files={"scan": ("q.npy", floats.getvalue())})
    assert r.status_code == 422 and "uint8" in r.json()["detail"]


def test_unknown_place_is_not_localized(client: httpx.Client) -> None:
    files = {"scan": ("q.png", _png(999, 0), "image/png")}
    res = client.post("/localize", data={"map_id": "route-a"}, files=files).json()
    assert res["status"] == "not_localized" and res["reason"] in ("too_few_inliers", "too_few_matches")
    assert res["pose"] is None and res["pose_uncertainty"] is None and res["motion_compensated"] is False


def test_bad_scan_inputs_get_4xx(client: httpx.Client) -> None:
    def post(files: dict, data: dict | None = None, path: str = "/localize") -> httpx.Response:
        return client.post(path, data=data if data is not None else {"map_id": "route-a"}, files=files)

    assert post({"scan": ("q.png", b"\x89PNG\r\n\x1a\n garbage")}).status_code == 422
    assert post({"scan": ("q.png", b"")}).status_code == 422
    small = encode_navtech_png_bytes(make_scan(1, 0))[:200]
    assert post({"scan": ("q.png", small)}).status_code == 422  # truncated
    import cv2

    ok, wrong_shape = cv2.imencode(".png", np.zeros((400, 600), np.uint8))
    r = post({"scan": ("q.png", wrong_shape.tobytes())})
    assert r.status_code == 422 and r.json()["error"] == "scan_format"
    buf = io.BytesIO()
    np.save(buf, np.full((400, 1000), np.nan, np.float32))
    assert post({"scan": ("q.npy", buf.getvalue())}).status_code == 422
    buf = io.BytesIO()
    np.save(buf, np.zeros((4, 4), np.uint8))
    r = post({"scan": ("q.npy", buf.getvalue())})
    assert r.status_code == 422 and "4 azimuths x 4 range bins" in r.json()["detail"]
    buf = io.BytesIO()
    np.save(buf, np.array(["a", "b"]))
    assert post({"scan": ("q.npy", buf.getvalue())}).status_code == 422
    assert post({"scan": ("q.png", b"0" * (4 * 2**20))}).status_code == 413
    assert post({"scan": ("q.png", _png(1, 0))}, data={"map_id": "nope"}).status_code == 404
    assert post({"scan": ("q.png", _png(1, 0))}, data={"map_id": "../x"}).status_code == 422
    assert post({"scan": ("q.png", _png(1, 0))}, data={"map_id": "route-a", "top_k": "0"}).status_code == 422
    assert post({"scan": ("q.png", _png(1, 0))}, data={"map_id": "route-a", "preset": "lidar"}).status_code == 400
    assert post({"other": ("q.png", _png(1, 0))}).status_code == 400
    assert client.post("/localize", json={"map_id": "route-a", "scan_id": "unknown"}).status_code == 404
    assert client.post("/localize", json={"scan_id": "x"}).status_code == 422
    assert client.post("/localize", content=b"{not json", headers={"content-type": "application/json"}).status_code == 422
    assert client.post("/localize", content=b"raw", headers={"content-type": "text/plain"}).status_code == 415
    assert client.post("/maps/nope/retrieve", json={"scan_id": "x"}).status_code == 404
    assert client.post("/scans", files={"scan": ("q.png", b"nope")}).status_code == 422
    assert client.get("/maps/..%2Fetc").status_code in (404, 422)
    assert client.delete("/maps/route-a").status_code == 401
    metrics = client.get("/metrics").text
    assert 'status="500"' not in metrics


def test_build_map_from_scan_archive_then_delete(client: httpx.Client, server: tuple[str, Path],
                                                 tmp_path: Path) -> None:
    n = 4
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for i in range(n):
            zf.writestr(f"radar/{keyframe_time(i)}.png", _png(i, keyframe_time(i)))
        zf.writestr("README.txt", "ignored")
        zf.writestr("../evil.png", b"ignored: not a timestamp name")
    poses = keyframe_poses()[:n]
    pose_file = write_txyyaw_csv(PoseSequence([keyframe_time(i) for i in range(n)], poses[:, :2], poses[:, 2]),
                                 tmp_path / "poses.csv")
    files = {"archive": ("scans.zip", buf.getvalue()), "poses": ("poses.csv", pose_file.read_bytes())}
    r = client.post("/maps", data={"map_id": "built", "preset": "boreas"}, files=files, headers=AUTH)
    assert r.status_code == 202, r.text
    assert r.json()["state"] in ("building", "ready") and r.json()["scans_total"] == n
    deadline = time.monotonic() + 60
    while (info := client.get("/maps/built").json())["state"] == "building" and time.monotonic() < deadline:
        time.sleep(0.1)
    assert info["state"] == "ready" and info["num_keyframes"] == n and info["progress"] == 1.0, info
    res = client.post("/localize", data={"map_id": "built"}, files={"scan": ("q.png", _png(2, 0))}).json()
    assert res["status"] == "localized" and res["keyframe"]["keyframe_id"] == 2
    # keyframe poses are taken at mid-sweep (docs/CONVENTIONS.md): 124.7 ms into the 0.25 s between keyframes
    track = PoseSequence([keyframe_time(i) for i in range(n)], poses[:, :2], poses[:, 2])
    mid = track.interpolate(mid_sweep_times_us(keyframe_time(2), get_preset("boreas")))
    assert res["pose"]["x_m"] == pytest.approx(mid[0], abs=0.05)
    assert not (server[1] / "evil.png").exists() and not (tmp_path.parent / "evil.png").exists()
    # bad archives and poses
    bad = {"archive": ("a.zip", b"not an archive"), "poses": ("p.csv", pose_file.read_bytes())}
    assert client.post("/maps", data={"map_id": "bad1"}, files=bad, headers=AUTH).status_code == 400
    bad = {"archive": ("scans.zip", buf.getvalue()), "poses": ("p.csv", b"\x00\xff\xfe binary")}
    assert client.post("/maps", data={"map_id": "bad2"}, files=bad, headers=AUTH).status_code == 422
    bad = {"archive": ("scans.zip", buf.getvalue())}
    assert client.post("/maps", data={"map_id": "bad3"}, files=bad, headers=AUTH).status_code == 400
    zbad = io.BytesIO()
    with zipfile.ZipFile(zbad, "w") as zf:
        zf.writestr(f"{keyframe_time(0)}.png", b"not a png")
    bad = {"archive": ("scans.zip", zbad.getvalue()), "poses": ("poses.csv", pose_file.read_bytes())}
    r = client.post("/maps", data={"map_id": "bad4"}, files=bad, headers=AUTH)
    assert r.status_code == 422 and f"{keyframe_time(0)}.png" in r.json()["detail"]
    assert client.get("/maps/bad4").status_code == 404  # nothing registered
    assert client.get("/maps/bad1").status_code == 404
    # delete
    assert client.delete("/maps/built", headers=AUTH).status_code == 200
    assert client.get("/maps/built").status_code == 404
    assert not (server[1] / "built.h5").exists()
    assert client.delete("/maps/built", headers=AUTH).status_code == 404


def test_python_client(server: tuple[str, Path], client: httpx.Client, tmp_path: Path) -> None:
    url, _ = server
    png = tmp_path / "q.png"
    png.write_bytes(_png(1, 77))
    with ReRadarClient(url, api_key=API_KEY) as rc:
        assert rc.wait_ready(timeout_s=5).status == "ready"
        assert any(m.id == "route-a" for m in rc.list_maps().data)
        res = rc.localize("route-a", scan_path=png)
        assert res.status == "localized" and res.keyframe is not None and res.keyframe.keyframe_id == 1
        sid = rc.upload_scan(png).scan_id
        assert rc.retrieve("route-a", scan_id=sid, top_k=2).keyframes[0].keyframe_id == 1
        for_map = rc.upload_scan(png, map_id="route-a")  # the map's preset, not a guess
        assert for_map.preset_assumed is False and rc.localize("route-a", scan_id=for_map.scan_id).status == "localized"
        assert rc.localize("route-a", scan_id=sid).status == "localized"
        with pytest.raises(ReRadarAPIError) as exc:
            rc.localize("missing", scan_path=png)
        assert exc.value.status_code == 404 and "unknown map" in exc.value.detail
