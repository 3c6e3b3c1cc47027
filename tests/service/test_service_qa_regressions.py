"""Regression tests for the black-box QA findings on the service (F1-F9): every one answers a clear 4xx (never a
500), vehicle positions need the vehicle routes' key, and the messages say what to do, without internals."""

from __future__ import annotations

import io
import struct
import sys
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import h5py
import httpx
import numpy as np
import pytest

from reradar_core.io.scan import encode_navtech_png_bytes
from service.api.security import AccessPolicy, route_class
from service.core.config import Settings
from service.core.errors import PROBLEM_MEDIA_TYPE, ConflictError, UnauthorizedError
from service.core.registry import MapEntry, MapRegistry

sys.path.insert(0, str(Path(__file__).resolve().parent))
import service_test_fakes as fakes  # noqa: E402
from service_test_fakes import API_KEY, FakeExtractor, register_map_file  # noqa: E402

keyframe_poses, keyframe_time, make_scan = fakes.keyframe_poses, fakes.keyframe_time, fakes.make_scan

AUTH = {"X-API-Key": API_KEY}
VEHICLE = "vehicle-key-0123456789"


def _problem(r: httpx.Response, status: int) -> dict:
    assert r.status_code == status, (r.status_code, r.text)
    assert r.headers["content-type"] == PROBLEM_MEDIA_TYPE
    body = r.json()
    assert body["status"] == status and "\n" not in body["detail"] and "/tmp" not in body["detail"]
    return body


@pytest.fixture(scope="module")
def client(server: tuple[str, Path], fake_map: Path) -> Iterator[httpx.Client]:
    url, _ = server
    with httpx.Client(base_url=url, timeout=60) as c:
        register_map_file(c, fake_map, "qa")
        yield c


def _png(i: int) -> bytes:
    return encode_navtech_png_bytes(make_scan(i, keyframe_time(i)))


def _archive(names: list[str]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for i, name in enumerate(names):
            zf.writestr(name, _png(i))
    return buf.getvalue()


def _poses_csv(n: int = 4, header: str = "t_s,x,y,yaw", yaw: np.ndarray | None = None) -> bytes:
    poses = keyframe_poses()[:n]
    yaw = poses[:, 2] if yaw is None else yaw
    lines = [header] + [f"{keyframe_time(i) / 1e6:.6f},{float(poses[i, 0])!r},{float(poses[i, 1])!r},{float(yaw[i])!r}"
                        for i in range(n)]
    return ("\n".join(lines) + "\n").encode()


# ---- F1: scan names beyond int64 ----------------------------------------------------------------------------

@pytest.mark.parametrize("stamp", ["99999999999999999999", "9999999999999999999", "5000000000000000000"])
def test_archive_scan_timestamp_out_of_range_is_400(client: httpx.Client, server: tuple[str, Path],
                                                    stamp: str) -> None:
    files = {"archive": ("a.zip", _archive([f"{stamp}.png"])), "poses": ("p.csv", _poses_csv())}
    body = _problem(client.post("/maps", data={"map_id": "ts-range"}, files=files, headers=AUTH), 400)
    assert f"'{stamp}.png'" in body["detail"] and "timestamp out of range" in body["detail"]
    assert "microseconds" in body["detail"]
    assert client.get("/maps/ts-range").status_code == 404
    assert not any(server[1].glob(".staging/job-*"))  # the unpacked archive was removed
    assert client.get("/healthz").status_code == 200  # the connection still serves


# ---- F2, F6: map validation on upload -----------------------------------------------------------------------

def _edited_map(fake_map: Path, tmp_path: Path, edit) -> Path:  # type: ignore[no-untyped-def]
    out = tmp_path / "edited.h5"
    out.write_bytes(fake_map.read_bytes())
    with h5py.File(out, "r+") as f:
        edit(f)
    return out


def _set(name: str, index: tuple[int, ...], value: float):  # type: ignore[no-untyped-def]
    def edit(f: h5py.File) -> None:
        f[name][index] = value
    return edit


def _link(name: str, link: object):  # type: ignore[no-untyped-def]
    def edit(f: h5py.File) -> None:
        f[name] = link
    return edit


@pytest.mark.parametrize(("edit", "words"), [
    (_set("keyframes/000000/keypoints_xy_m", (0, 0), np.nan), "keypoints must be finite"),
    (_set("keyframes/000001/keypoints_xy_m", (0, 0), 1e30), "within the radar's range (250 m)"),
    (_set("keyframes/000002/keypoints_xy_m", (0, 1), 2500.0), "within the radar's range (250 m)"),
    (_set("keyframes/000003/local_descriptors", (0, 0), np.nan), "local_descriptors contain NaN"),
    (_set("poses", (1, 1), 1e300), "keyframe poses must lie within"),
    (_link("keyframes/000005/ext", h5py.ExternalLink("/etc/passwd", "/x")), "external link"),
    (_link("alias", h5py.SoftLink("/poses")), "soft link"),
], ids=["nan-keypoint", "1e30-keypoint", "2500m-keypoint", "nan-local-descriptor", "far-pose", "external-link",
        "soft-link"])
def test_invalid_map_upload_is_422_map_format_and_nothing_is_stored(
        client: httpx.Client, server: tuple[str, Path], fake_map: Path, tmp_path: Path, edit, words: str) -> None:  # type: ignore[no-untyped-def]
    bad = _edited_map(fake_map, tmp_path, edit)
    r = client.post("/maps", data={"map_id": "badmap"}, files={"map_file": ("m.h5", bad.read_bytes())}, headers=AUTH)
    body = _problem(r, 422)
    assert body["error"] == "map_format" and words in body["detail"], body
    assert body["detail"].startswith("the uploaded map: ") and "badmap" not in body["detail"]
    assert client.get("/maps/badmap").status_code == 404
    assert not (server[1] / "badmap.h5").exists()
    assert client.post("/localize", data={"map_id": "qa"}, files={"scan": ("q.png", _png(2))}).status_code == 200


# ---- F3: vehicle positions behind the vehicle routes' rule ----------------------------------------------------

def test_ui_data_routes_are_vehicle_routes() -> None:
    for path in ("/ui/api/maps/x/localizations", "/ui/api/maps/x/trajectory"):
        assert route_class("GET", path) == "vehicle"
    assert route_class("GET", "/") == "public" and route_class("GET", "/ui/static/app.js") == "public"
    assert route_class("GET", "/maps") == "public"
    # without vehicle keys: loopback only; a remote client without a key is refused
    policy = AccessPolicy("o" * 20)
    assert policy.authorize(route_class("GET", "/ui/api/maps/x/trajectory"), None, "127.0.0.1") == "loopback"
    with pytest.raises(UnauthorizedError):
        policy.authorize(route_class("GET", "/ui/api/maps/x/localizations"), None, "192.0.2.2")


def test_ui_data_needs_a_key_when_vehicle_keys_are_configured(tmp_path: Path, fake_map: Path) -> None:
    from service.demo import serve_in_thread

    settings = Settings(maps_dir=tmp_path / "maps", load_demo_map=False, api_key=API_KEY, vehicle_keys=VEHICLE)
    with serve_in_thread(settings, FakeExtractor()) as url, httpx.Client(base_url=url, timeout=30) as c:
        register_map_file(c, fake_map, "k")
        r = c.post("/localize", data={"map_id": "k"}, files={"scan": ("q.png", _png(1))}, headers={"X-API-Key": VEHICLE})
        assert r.status_code == 200 and r.json()["status"] == "localized", r.text
        for path in ("/ui/api/maps/k/localizations", "/ui/api/maps/k/trajectory"):
            _problem(c.get(path), 401)
            _problem(c.get(path, headers={"X-API-Key": "wrong-key-0123456789"}), 401)
            for key in (VEHICLE, API_KEY):
                assert c.get(path, headers={"X-API-Key": key}).status_code == 200
        fixes = c.get("/ui/api/maps/k/localizations", headers={"X-API-Key": VEHICLE}).json()["data"]
        assert [f["keyframe_id"] for f in fixes] == [1]
        traj = c.get("/ui/api/maps/k/trajectory", headers={"X-API-Key": API_KEY}).json()
        np.testing.assert_allclose(traj["x_m"], keyframe_poses()[:, 0], atol=1e-3)
        assert c.get("/maps").status_code == 200 and c.get("/").status_code == 200  # still public


# ---- F4: yaw unit of the t,x,y,yaw pose upload ------------------------------------------------------------------

def test_pose_upload_with_degrees_in_a_plain_yaw_column_is_refused(client: httpx.Client) -> None:
    deg = np.degrees(keyframe_poses()[:4, 2]) + 80.0  # up to ~123 degrees
    files = {"archive": ("a.zip", _archive([f"{keyframe_time(i)}.png" for i in range(4)])),
             "poses": ("p.csv", _poses_csv(yaw=deg))}
    body = _problem(client.post("/maps", data={"map_id": "deg"}, files=files, headers=AUTH), 422)
    assert body["error"] == "pose_file" and "yaw_deg" in body["detail"] and "radians" in body["detail"]
    far = _poses_csv().replace(b",-3.0,", b",-3e300,")
    assert far != _poses_csv()
    files = {"archive": files["archive"], "poses": ("p.csv", far)}
    body = _problem(client.post("/maps", data={"map_id": "far"}, files=files, headers=AUTH), 422)
    assert "1e+07 m" in body["detail"]
    assert client.get("/maps/deg").status_code == 404 and client.get("/maps/far").status_code == 404


def test_pose_upload_with_a_yaw_deg_header_builds_the_right_headings(client: httpx.Client) -> None:
    n = 4
    yaw = np.array([90.0, 90.0, 90.0, 90.0])
    files = {"archive": ("a.zip", _archive([f"{keyframe_time(i)}.png" for i in range(n)])),
             "poses": ("p.csv", _poses_csv(n, "t_s,x,y,yaw_deg", yaw))}
    traj = _built_trajectory(client, "degmap", files)
    np.testing.assert_allclose(traj["yaw_deg"], [90.0] * n, atol=0.01)
    assert client.delete("/maps/degmap", headers=AUTH).status_code == 200


def _built_trajectory(client: httpx.Client, map_id: str, files: dict) -> dict:
    """``POST /maps`` (202), wait up to 60 s for the build, and return the map's keyframe trajectory."""
    r = client.post("/maps", data={"map_id": map_id, "preset": "boreas"}, files=files, headers=AUTH)
    assert r.status_code == 202, r.text
    deadline = time.monotonic() + 60
    while client.get(f"/maps/{map_id}").json()["state"] == "building" and time.monotonic() < deadline:
        time.sleep(0.1)
    return client.get(f"/ui/api/maps/{map_id}/trajectory").json()


# ---- F7: messages -------------------------------------------------------------------------------------------

def _npy_bytes(version: int, header: bytes, declared_len: int | None = None) -> bytes:
    if version == 1:
        return b"\x93NUMPY\x01\x00" + struct.pack("<H", declared_len or len(header)) + header
    return b"\x93NUMPY" + bytes([version, 0]) + struct.pack("<I", declared_len or len(header)) + header


def test_scan_errors_say_what_is_wrong_without_internals(client: httpx.Client) -> None:
    def post(data: bytes, name: str = "q.npy") -> str:
        return _problem(client.post("/scans", files={"scan": (name, data)}), 422)["detail"]

    call = b"{'descr': __import__('os').system('x'), 'fortran_order': False, 'shape': (400, 500), }".ljust(127) + b"\n"
    detail = post(_npy_bytes(1, call))
    assert "malformed .npy header" in detail and "0x" not in detail and "ast" not in detail
    detail = post(_npy_bytes(3, b"{}".ljust(63) + b"\n", declared_len=662372470) + bytes(1000))
    assert "truncated or oversized .npy header" in detail and "662372470" not in detail and "65524" not in detail
    detail = post(_npy_bytes(9, b"{}\n"))
    assert "unsupported .npy format version 9.0" in detail
    for dtype in (np.int16, np.uint16, np.int64):
        buf = io.BytesIO()
        np.save(buf, np.full((400, 500), 200, dtype))
        detail = post(buf.getvalue())
        assert "non-uint8 polar array" in detail and "[0, 1]" in detail and "float polar" not in detail
    ok, tiny = cv2.imencode(".png", np.zeros((10, 10), np.uint8))
    detail = post(tiny.tobytes(), "q.png")
    assert "10 azimuths x 0 range bins" in detail and "-1" not in detail and "11 of which" in detail


def test_archive_that_is_no_archive_gets_one_line(client: httpx.Client) -> None:
    files = {"archive": ("a.zip", b"this is not an archive" * 10), "poses": ("p.csv", _poses_csv())}
    body = _problem(client.post("/maps", data={"map_id": "noarch"}, files=files, headers=AUTH), 400)
    assert body["detail"] == "scan archive is not a .zip, .tar or .tar.gz archive"


def test_non_finite_json_numbers_say_finite(client: httpx.Client) -> None:
    for value in (b"NaN", b"Infinity", b"-Infinity"):
        raw = (b'{"map_id": "qa", "scan_id": "s", "session_id": "v1", "odom_dx_m": ' + value
               + b', "odom_dy_m": 0, "odom_dyaw_deg": 0}')
        r = client.post("/localize", content=raw, headers={"content-type": "application/json"})
        body = _problem(r, 422)
        assert "finite number" in body["detail"] and "less than" not in body["detail"], body


def test_post_for_an_id_being_built_says_to_wait(tmp_path: Path) -> None:
    registry = MapRegistry(Settings(maps_dir=tmp_path / "maps", load_demo_map=False, api_key=API_KEY), FakeExtractor())
    try:
        registry._entries["bld"] = MapEntry("bld", registry.path_for("bld"), "building", scans_done=1, scans_total=4)
        with pytest.raises(ConflictError, match=r"being built \(25%\); wait until the build finishes") as err:
            registry._reserve("bld")
        assert "DELETE /maps/bld first" not in str(err.value)
        with pytest.raises(ConflictError, match="being built; wait"):  # and DELETE agrees
            registry.delete("bld")
        registry._entries["bld"].state = "failed"
        with pytest.raises(ConflictError, match="DELETE /maps/bld first"):
            registry._reserve("bld")
    finally:
        registry.close()


# ---- F8: metrics of refused requests, 405 before 401, HEAD on health ----------------------------------------

def test_guard_refusals_count_under_their_route_and_405_before_401(client: httpx.Client) -> None:
    _problem(client.post("/maps", data={"map_id": "x"}), 401)
    _problem(client.delete("/maps/qa"), 401)
    metrics = client.get("/metrics").text
    assert 'reradar_http_requests_total{method="POST",route="/maps",status="401"}' in metrics
    assert 'reradar_http_requests_total{method="DELETE",route="/maps/{map_id}",status="401"}' in metrics
    # an unsupported method is 405 with or without a key (Allow lists the path's methods)
    for headers in ({}, AUTH, {"X-API-Key": "wrong-key-0123456789"}):
        r = client.put("/maps", headers=headers)
        _problem(r, 405)
        assert set(r.headers["allow"].split(", ")) == {"GET", "POST"}
        r = client.patch("/maps/qa", headers=headers)
        _problem(r, 405)
        assert set(r.headers["allow"].split(", ")) == {"DELETE", "GET"}
        # a static file of the operator page: 405 too (was 401 without a key, and an empty Allow with one)
        for method in ("POST", "PUT", "DELETE"):
            r = client.request(method, "/ui/static/app.js", headers=headers)
            assert "allowed: GET, HEAD" in _problem(r, 405)["detail"]
            assert r.headers["allow"] == "GET, HEAD"
    assert client.get("/ui/static/app.js").status_code == 200
    assert client.options("/ui/static/app.js").headers["allow"] == "GET, HEAD"
    metrics = client.get("/metrics").text
    assert 'reradar_http_requests_total{method="PUT",route="/maps",status="405"}' in metrics
    # an unknown path still needs a key for a write method (safe by default)
    _problem(client.post("/nowhere", headers={"X-API-Key": "wrong-key-0123456789"}), 401)


def test_head_on_health_endpoints(client: httpx.Client) -> None:
    for path in ("/healthz", "/readyz", "/"):
        r = client.head(path)
        assert r.status_code == 200 and r.content == b""


# ---- F9: ambiguous credentials, wrong encodings ------------------------------------------------------------

def test_duplicate_api_key_headers_are_refused(client: httpx.Client) -> None:
    for pair in (["wrong-key-0123456789", API_KEY], [API_KEY, "wrong-key-0123456789"], [API_KEY, API_KEY]):
        headers = [("X-API-Key", k) for k in pair]
        body = _problem(client.post("/maps", data={"map_id": "dup"}, headers=headers), 400)
        assert "ambiguous credentials" in body["detail"] and "X-API-Key" in body["detail"]
        r = client.post("/localize", data={"map_id": "qa"}, files={"scan": ("q.png", _png(2))}, headers=headers)
        _problem(r, 400)
    assert client.get("/maps/dup").status_code == 404


def test_repeated_form_fields_on_localize_are_refused(client: httpx.Client) -> None:
    """``map_id=qa&map_id=other`` must not silently localize on the last map named."""
    r = client.post("/localize", data={"map_id": ["qa", "other"]}, files={"scan": ("q.png", _png(2))})
    body = _problem(r, 400)
    assert "map_id" in body["detail"] and "more than once" in body["detail"]


def test_json_body_on_multipart_routes_is_415(client: httpx.Client) -> None:
    body = _problem(client.post("/maps", json={"map_id": "j"}, headers=AUTH), 415)
    assert "multipart/form-data" in body["detail"] and "application/json" in body["detail"]
    body = _problem(client.post("/scans", json={"scan": "x"}), 415)
    assert "multipart/form-data" in body["detail"]


@pytest.mark.parametrize("url, message", [("redis://h:6379/0/", "not a database number"),
                                          ("redis://h:6379/abc", "not a database number"),
                                          ("http://h:6379", "not a Redis URL")])
def test_a_redis_url_both_clients_cannot_read_alike_is_refused(tmp_path, url, message) -> None:
    """QA (session 20): ``/0/`` or ``/abc`` was accepted at start-up (redis-py ignores the path) and every queued
    build then answered 500 (arq's parser refused it); a percent-encoded password worked for one client only."""
    from pydantic import ValidationError

    from service.core.shared_state import arq_redis_settings

    with pytest.raises(ValidationError, match=message):
        Settings(maps_dir=tmp_path, redis_url=url)
    rs = arq_redis_settings("redis://:p%40ss%2Fw0rd@127.0.0.1:6380/3")
    assert (rs.password, rs.port, rs.database) == ("p@ss/w0rd", 6380, 3)


def test_unreadable_shared_values_are_unknown_not_a_500() -> None:
    """QA (session 20): a value in the namespace this version did not write answered 500."""
    from service.core.shared_state import Keys, RecentLocalizations, RedisScanStore

    class FakeRedis:
        def get(self, key):  # noqa: ANN001, ANN202
            return b"garbage"

        def lrange(self, key, a, b):  # noqa: ANN001, ANN202
            return [b"garbage", b'{"status": "localized"}', b"[1, 2]"]

    assert RedisScanStore(FakeRedis(), Keys(), 60.0).get("0" * 32) is None  # type: ignore[arg-type]
    recent = RecentLocalizations(10, FakeRedis(), Keys())  # type: ignore[arg-type]
    assert recent.latest("demo", 5) == [{"status": "localized"}]


def test_sessions_skip_a_failing_redis_for_a_while() -> None:
    """QA (session 20): on a hung Redis every tracked scan waited two 2 s timeouts while holding a request slot;
    after a failure the sessions skip Redis for ``BACKOFF_S`` (the scans are localized globally meanwhile)."""
    import numpy as np
    import redis

    from reradar_core.localization import PosePrior
    from service.core.shared_state import Keys, RedisSessionStore

    class HungRedis:
        calls = 0

        def get(self, key):  # noqa: ANN001, ANN202
            HungRedis.calls += 1
            raise redis.TimeoutError("timed out")

        def set(self, *a, **k):  # noqa: ANN002, ANN003, ANN202
            HungRedis.calls += 1
            raise redis.TimeoutError("timed out")

    store = RedisSessionStore(HungRedis(), Keys())  # type: ignore[arg-type]
    assert store.get("s", "demo") is None and HungRedis.calls == 1
    for _ in range(5):
        assert store.get("s", "demo") is None
        store._store("s", "demo", PosePrior(np.zeros(3), 1.0, 0.1))
    assert HungRedis.calls == 1  # skipped for BACKOFF_S


def test_scan_id_with_a_guessed_preset_is_refused_on_a_map_of_another_geometry(
        client: httpx.Client, tmp_path: Path, fake_extractor: FakeExtractor) -> None:
    """QA (session 21): ``POST /scans`` read a 3,360-bin PNG as boreas (0.0596 m bins) without a word, and a
    ``scan_id`` localization on a boreas-2021 map (0.04381 m) then ran with every range 1.36x too long, where the
    same file sent inline took the map's preset. The guess is now reported (``preset_assumed``) and refused on a
    map of another geometry; ``map_id`` on upload gives the inline behaviour."""
    from maps.build import build_map
    from service.core.shared_state import decode_features, encode_features

    map21 = build_map(tmp_path / "m21.h5", fake_extractor,
                      lambda i: make_scan(i, keyframe_time(i), preset="boreas-2021"), keyframe_poses(),
                      radar_preset="boreas-2021", name="qa21", batch_size=4)
    register_map_file(client, map21, "qa21")
    png = ("q.png", _png(3))

    guessed = client.post("/scans", files={"scan": png})
    assert guessed.status_code == 201, guessed.text
    assert guessed.json()["preset"] == "boreas" and guessed.json()["preset_assumed"] is True
    sid = guessed.json()["scan_id"]
    # the guess is the map's own preset: nothing to refuse
    assert client.post("/localize", json={"scan_id": sid, "map_id": "qa"}).status_code == 200
    for r in (client.post("/localize", json={"scan_id": sid, "map_id": "qa21"}),
              client.post("/maps/qa21/retrieve", json={"scan_id": sid})):
        detail = _problem(r, 422)["detail"]
        assert "preset=boreas-2021" in detail and "0.0596" in detail and "0.04381" in detail

    # uploaded for the map: its preset, no guess; an explicit preset is the client's word and is kept
    for data, preset in (({"map_id": "qa21"}, "boreas-2021"), ({"preset": "boreas"}, "boreas")):
        r = client.post("/scans", data=data, files={"scan": png})
        assert r.status_code == 201 and r.json()["preset"] == preset and r.json()["preset_assumed"] is False
        assert client.post("/localize", json={"scan_id": r.json()["scan_id"], "map_id": "qa21"}).status_code == 200
    # QA re-test: a scan uploaded for one map (its preset taken from that map, not from the client) is refused on
    # a map of another geometry like a guessed one
    for_qa = client.post("/scans", data={"map_id": "qa"}, files={"scan": png}).json()
    assert for_qa["preset"] == "boreas" and for_qa["preset_assumed"] is False
    detail = _problem(client.post("/localize", json={"scan_id": for_qa["scan_id"], "map_id": "qa21"}), 422)["detail"]
    assert "read with the boreas preset" in detail and "preset=boreas-2021" in detail
    _problem(client.post("/scans", data={"map_id": "nosuch"}, files={"scan": png}), 404)
    assert client.delete("/maps/qa21", headers=AUTH).status_code == 200

    # the fleet's Redis blob carries the flag; one written before it reads as not open
    feats = fake_extractor.describe(make_scan(1, keyframe_time(1)))
    assert decode_features(encode_features(feats, "boreas", True))[1:] == ("boreas", True, None, None)
    buf = io.BytesIO()
    np.savez(buf, global_descriptor=feats.global_descriptor, keypoints_xy_m=feats.keypoints_xy_m,
             local_descriptors=feats.local_descriptors, timestamp_us=np.int64(1), preset=np.array("boreas"))
    assert decode_features(buf.getvalue())[1:] == ("boreas", False, None, None)


def test_relative_pose_times_over_http_get_advice_that_works_over_http(client: httpx.Client) -> None:
    """QA (session 21): POST /maps with a t,x,y,yaw CSV starting at 0 s answered with command-line advice
    (--time-unit, time_unit=) that the HTTP API has no field for."""
    poses = keyframe_poses()[:4]
    csv = "t,x,y,yaw\n" + "".join(f"{0.25 * i},{float(poses[i, 0])},{float(poses[i, 1])},0.0\n" for i in range(4))
    files = {"archive": ("a.zip", _archive([f"{keyframe_time(i)}.png" for i in range(4)])),
             "poses": ("p.csv", csv.encode())}
    detail = _problem(client.post("/maps", data={"map_id": "rel-times"}, files=files, headers=AUTH), 422)["detail"]
    assert "ambiguous" in detail and "t_s,x,y,yaw" in detail
    assert "--time-unit" not in detail and "time_unit=" not in detail


def test_made_up_methods_cannot_grow_the_metrics(client: httpx.Client) -> None:
    """QA (session 21): every invented method name (`curl -X QA123`) became new metric series: 25,000 requests
    made /metrics 45 MB. Unknown methods now count as `other`."""
    for i in range(20):
        client.request(f"QA{i}X", "/healthz")
    metrics = client.get("/metrics").text
    assert "QA0X" not in metrics and "QA19X" not in metrics
    assert 'reradar_http_requests_total{method="other",route="/healthz",' in metrics


def test_localizations_of_an_unknown_map_are_404(client: httpx.Client) -> None:
    """QA (session 21): the operator page's localizations route answered 200 with no data for an unknown map,
    where every other map route answers 404."""
    body = _problem(client.get("/ui/api/maps/no-such-map/localizations"), 404)
    assert "unknown map 'no-such-map'" in body["detail"]
    assert client.get("/ui/api/maps/qa/localizations").status_code == 200


def test_a_place_that_fits_twice_is_ambiguous_not_a_guess(client: httpx.Client, tmp_path: Path,
                                                          fake_extractor: FakeExtractor) -> None:
    """QA (session 21): a map holding one drive twice, 500 m apart (two GNSS offsets, look-alike streets), answered
    6 of 8 queries `localized` on the wrong copy at confidence 0.9998: the tie with a candidate at another place
    lowered the confidence's margin cue but did not refuse. `min_place_margin` now makes such a tie `ambiguous`."""
    from maps.build import build_map

    n = fakes.N_KEYFRAMES
    poses = keyframe_poses()
    twice = np.concatenate([poses, poses + np.array([500.0, 0.0, 0.0])])
    path = build_map(tmp_path / "twice.h5", fake_extractor, lambda i: make_scan(i % n, keyframe_time(i)), twice,
                     radar_preset="boreas", name="twice", batch_size=4)
    register_map_file(client, path, "twice")
    for i in (2, 5):
        scan = {"scan": ("q.png", _png(i))}
        res = client.post("/localize", data={"map_id": "twice"}, files=scan).json()
        assert res["status"] == "not_localized" and res["reason"] == "ambiguous" and res["pose"] is None
        # the same scan on the map with one copy of the drive: localized at its keyframe
        one = client.post("/localize", data={"map_id": "qa"}, files=scan).json()
        assert one["status"] == "localized" and one["keyframe"]["keyframe_id"] == i
    assert client.delete("/maps/twice", headers=AUTH).status_code == 200


def test_two_scan_files_on_localize_are_named_as_repeated(client: httpx.Client) -> None:
    """QA re-test (session 21): two `scan` files on /localize were refused as "Too many files" by the parser."""
    files = [("scan", ("a.png", _png(1))), ("scan", ("b.png", _png(2)))]
    detail = _problem(client.post("/localize", data={"map_id": "qa"}, files=files), 400)["detail"]
    assert "['scan'] are given more than once" in detail


def test_pose_times_whose_header_names_another_unit_than_their_values_are_refused(client: httpx.Client) -> None:
    """QA (session 23, high): scans named by relative microseconds and a pose CSV whose header says t_s (or t_ms)
    over microsecond values built a `ready` map whose keyframes all lay within 0.06 mm of the drive's start,
    then answered `localized` 56 m off at confidence 1.0. Such an upload is now a 422 naming the unit to declare,
    and the same file with the right header builds."""
    n = 4
    poses = keyframe_poses()[:n]  # 40 m apart: a 120 m drive
    stamps = [1_000_000 + 250_000 * i for i in range(n)]  # relative microseconds, as the QA's scan names
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:  # each scan carries its name's time (else refused: another instant)
        for i, t in enumerate(stamps):
            zf.writestr(f"{t}.png", encode_navtech_png_bytes(make_scan(i, t)))
    archive = buf.getvalue()

    def csv(header: str) -> bytes:
        rows = [f"{t},{float(p[0])!r},{float(p[1])!r},{float(p[2])!r}" for t, p in zip(stamps, poses, strict=True)]
        return ("\n".join([header, *rows]) + "\n").encode()

    for header, map_id in (("t_s,x,y,yaw", "unit-s"), ("t_ms,x,y,yaw", "unit-ms")):
        files = {"archive": ("a.zip", archive), "poses": ("p.csv", csv(header))}
        body = _problem(client.post("/maps", data={"map_id": map_id, "preset": "boreas"}, files=files, headers=AUTH),
                        422)
        assert body["error"] == "pose_file" and "t_us" in body["detail"], body
        assert "--time-unit" not in body["detail"]
        assert client.get(f"/maps/{map_id}").status_code == 404
    files = {"archive": ("a.zip", archive), "poses": ("p.csv", csv("t_us,x,y,yaw"))}
    traj = _built_trajectory(client, "unit-us", files)
    assert traj["x_m"][-1] > 100.0  # keyframes spread along the drive
    assert client.delete("/maps/unit-us", headers=AUTH).status_code == 200
