"""Regression tests for the black-box QA of session 36: tracking sessions are the caller's own and end with their
map's version, file fields sent as text get a plain 400, client text is not echoed at length, form numbers are
ASCII decimals only, a far-view companion of another radar preset is refused, headings on the operator page stay
in (-180, 180] and an uploaded map being checked says so."""

from __future__ import annotations

import math
import shutil
import sys
from pathlib import Path

import h5py
import httpx
import numpy as np
import pytest

from maps.build import build_map
from maps.database import far_view_mismatch
from reradar_core.geometry.se2 import relative_pose
from reradar_core.io.scan import encode_navtech_png_bytes
from service.core.config import Settings
from service.core.errors import PROBLEM_MEDIA_TYPE, ConflictError
from service.core.registry import UPLOAD_CHECK_NOTE, MapEntry, MapRegistry, last_pass_note

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import (  # noqa: E402
    API_KEY,
    FakeExtractor,
    keyframe_poses,
    keyframe_time,
    make_scan,
    register_map_file,
)

AUTH = {"X-API-Key": API_KEY}
KEY_A, KEY_B = "vehicle-key-A-0123456789", "vehicle-key-B-0123456789"


def _problem(r: httpx.Response, status: int) -> dict:
    assert r.status_code == status, (r.status_code, r.text)
    assert r.headers["content-type"] == PROBLEM_MEDIA_TYPE
    body = r.json()
    assert "\n" not in body["detail"] and "/tmp" not in body["detail"] and "UploadFile" not in body["detail"]
    return body


def _png(i: int) -> bytes:
    return encode_navtech_png_bytes(make_scan(i, keyframe_time(i)))


def _localize(c: httpx.Client, key: str, seed: int, map_id: str = "m", **fields: object) -> dict:
    r = c.post("/localize", data={"map_id": map_id, **{k: str(v) for k, v in fields.items()}},
               files={"scan": ("q.png", _png(seed))}, headers={"X-API-Key": key})
    assert r.status_code == 200, r.text
    return r.json()


def _creep(i: int) -> dict[str, float]:
    """Odometry of 0.2 m straight on from keyframe ``i``: tracked when the session's last pose is keyframe i's."""
    p = keyframe_poses()[i]
    odo = relative_pose(p, p + [0.2 * math.cos(p[2]), 0.2 * math.sin(p[2]), 0.0])
    return {"odom_dx_m": float(odo[0]), "odom_dy_m": float(odo[1]), "odom_dyaw_deg": 0.0}


def test_a_session_is_the_callers_own_and_ends_with_its_maps_version(tmp_path: Path, fake_map: Path) -> None:
    from service.demo import serve_in_thread

    shifted = tmp_path / "shifted.h5"  # another map of the same scans, 30 m over: another frame
    poses = keyframe_poses() + [30.0, 0.0, 0.0]
    build_map(shifted, FakeExtractor(), lambda i: make_scan(i, keyframe_time(i)), poses, radar_preset="boreas",
              name="shifted", batch_size=4)
    settings = Settings(maps_dir=tmp_path / "maps", load_demo_map=False, api_key=API_KEY,
                        vehicle_keys=f"{KEY_A},{KEY_B}")
    with serve_in_thread(settings, FakeExtractor()) as url, httpx.Client(base_url=url, timeout=60) as c:
        register_map_file(c, fake_map, "m")
        assert _localize(c, KEY_A, 2, session_id="truck-7")["keyframe"]["keyframe_id"] == 2
        # another key's vehicle under the same id: its own session, A's is neither read nor moved
        other = _localize(c, KEY_B, 4, session_id="truck-7", **_creep(2))
        assert other["mode"] == "global" and not other["tracking_lost"] and other["keyframe"]["keyframe_id"] == 4
        tracked = _localize(c, KEY_A, 2, session_id="truck-7", **_creep(2))
        assert tracked["mode"] == "tracking" and tracked["status"] == "localized", tracked
        # the map replaced under its id: the session's pose was in the old map's frame, so it starts afresh
        assert c.delete("/maps/m", headers=AUTH).status_code in (200, 204)
        register_map_file(c, shifted, "m")
        fresh = _localize(c, KEY_A, 2, session_id="truck-7", **_creep(2))
        assert fresh["mode"] == "global" and not fresh["tracking_lost"], fresh
        assert fresh["pose"]["x_m"] == pytest.approx(poses[2, 0], abs=0.3)


@pytest.fixture(scope="module")
def client(server: tuple[str, Path], fake_map: Path) -> httpx.Client:
    url, _ = server
    with httpx.Client(base_url=url, timeout=60) as c:
        register_map_file(c, fake_map, "q36")
        yield c


def test_file_fields_sent_as_text_get_a_plain_400(client: httpx.Client) -> None:
    # a multipart part without a file name is a text field (curl -F "scan=<file.png")
    body = _problem(client.post("/scans", files={"scan": (None, "not a file")}), 400)
    assert "'scan' arrived as text" in body["detail"] and "-F scan=@path" in body["detail"]
    body = _problem(client.post("/maps", files={"map_id": (None, "x36"), "map_file": (None, "hello")},
                                headers=AUTH), 400)
    assert "'map_file' arrived as text" in body["detail"]
    body = _problem(client.post("/maps", data={"map_id": "x36", "map_file": "hello"}, headers=AUTH), 400)
    assert "'map_file' arrived as text" in body["detail"]
    body = _problem(client.post("/localize", files={"map_id": (None, "q36"), "scan": (None, "abc")}), 400)
    assert "'scan' arrived as text" in body["detail"]
    assert client.get("/maps/x36").status_code == 404  # nothing registered


def test_empty_optional_file_fields_are_not_given(client: httpx.Client, fake_map: Path) -> None:
    """An empty value is "not given" (a script that always sends every field): the map is registered (code review,
    session 36: refused as 'arrived as text')."""
    with fake_map.open("rb") as fh:
        r = client.post("/maps", files={"map_id": (None, "empty36"), "map_file": ("m.h5", fh), "far_map_file": (None, ""),
                                        "poses": (None, ""), "archive": (None, "")}, headers=AUTH)
    assert r.status_code == 201, r.text
    assert client.delete("/maps/empty36", headers=AUTH).status_code in (200, 204)


def test_the_callers_namespace_is_a_keyed_digest() -> None:
    """Sessions are namespaced by an HMAC of the API key under the operator key: stable, one per key, and no plain
    hash of the key (which a low-entropy key could be found from) appears in Redis keys or logs."""
    import hashlib

    from service.api.security import AccessPolicy

    policy = AccessPolicy("operator-key-0123456789", (KEY_A, KEY_B))
    a, b = policy.caller_id("vehicle", KEY_A), policy.caller_id("vehicle", KEY_B)
    assert a == policy.caller_id("vehicle", KEY_A) and a != b and a.startswith("key-")
    assert hashlib.sha256(KEY_A.encode()).hexdigest()[:16] not in a
    assert AccessPolicy("another-operator-key-0123", (KEY_A,)).caller_id("vehicle", KEY_A) != a
    assert policy.caller_id("loopback", None) == "loopback"


def test_a_long_field_name_is_not_echoed_at_length(client: httpx.Client) -> None:
    name = "a" * 200_000
    r = client.post("/localize", content=b'{"' + name.encode() + b'": 1, "map_id": "q36", "scan_id": "x"}',
                    headers={"content-type": "application/json"})
    body = _problem(r, 422)
    assert len(r.content) < 4_000 and "200,000 characters" in r.text, len(r.content)
    assert body["errors"][0]["loc"][-1].startswith("aaaa")
    form = client.post("/localize", data={"map_id": "q36", "b" * 5_000: "1"}, files={"scan": ("q.png", _png(1))})
    assert form.status_code == 400 and len(form.content) < 2_000, (form.status_code, len(form.content))


@pytest.mark.parametrize("field, text", [("top_k", "5\n"), ("top_k", "\u0665"), ("prior_x_m", "\u0663"),
                                         ("prior_x_m", "1.0\n")])
def test_form_numbers_are_ascii_decimals_only(client: httpx.Client, field: str, text: str) -> None:
    fields = {"map_id": "q36", field: text}
    if field.startswith("prior"):
        fields.update(prior_y_m="0", prior_yaw_deg="0")
    r = client.post("/localize", data=fields, files={"scan": ("q.png", _png(1))})
    _problem(r, 422)
    assert field in r.text


class _Keyframes:
    def __init__(self, poses: np.ndarray) -> None:
        self.poses, self.timestamps_us = poses, np.arange(len(poses), dtype=np.int64)

    def __len__(self) -> int:
        return len(self.poses)


def test_a_far_view_companion_of_another_radar_preset_is_refused() -> None:
    near, far = _Keyframes(keyframe_poses()), _Keyframes(keyframe_poses().copy())
    assert far_view_mismatch(near, far) is None and far_view_mismatch(near, far, ("boreas", "boreas")) is None
    assert "radar preset 'oxford', the map's of 'boreas'" in far_view_mismatch(near, far, ("boreas", "oxford"))


def test_far_companion_upload_of_another_preset_is_422(client: httpx.Client, tmp_path: Path, fake_map: Path) -> None:
    far = tmp_path / "far.h5"
    shutil.copy(fake_map, far)  # the same keyframes; only its preset differs (the view is not what is tested)
    with h5py.File(far, "r+") as fh:
        fh.attrs["radar_preset"] = "oxford"
    with fake_map.open("rb") as m, far.open("rb") as f:
        r = client.post("/maps", data={"map_id": "farp"}, files={"map_file": ("m.h5", m), "far_map_file": ("f.h5", f)},
                        headers=AUTH)
    assert r.status_code in (400, 409, 422), r.text  # refused (which check refuses it first depends on the service)
    assert client.get("/maps/farp").status_code == 404


def test_trajectory_headings_are_wrapped(client: httpx.Client, tmp_path: Path, fake_map: Path) -> None:
    odd = tmp_path / "odd.h5"
    shutil.copy(fake_map, odd)
    with h5py.File(odd, "r+") as fh:
        poses = fh["poses"][...]
        poses[3, 2] = 1000.0  # a heading stored unwrapped: 1000 rad
        fh["poses"][...] = poses
    register_map_file(client, odd, "odd36")
    yaw = client.get("/ui/api/maps/odd36/trajectory").json()["yaw_deg"]
    assert all(-180.0 < y <= 180.0 for y in yaw)
    expected = math.degrees(math.atan2(math.sin(1000.0), math.cos(1000.0)))
    assert yaw[3] == pytest.approx(expected, abs=0.01)


def test_an_uploaded_map_being_checked_says_so(tmp_path: Path) -> None:
    registry = MapRegistry(Settings(maps_dir=tmp_path / "maps", load_demo_map=False, api_key=API_KEY), FakeExtractor())
    try:
        entry = MapEntry("up", registry.path_for("up"), "building", uploaded=True)
        registry._entries["up"] = entry
        assert last_pass_note(entry) == UPLOAD_CHECK_NOTE and "no build job" in UPLOAD_CHECK_NOTE
        with pytest.raises(ConflictError, match="uploaded map file is being checked.*retry the DELETE"):
            registry.delete("up")
        with pytest.raises(ConflictError, match="uploaded map file is being checked.*retry then"):
            registry.ready("up")
        with pytest.raises(ConflictError, match="is taken: the uploaded map file"):
            registry._reserve("up")
        entry.uploaded = False  # a build job: the build's own messages
        with pytest.raises(ConflictError, match="being built; wait for the job"):
            registry.delete("up")
    finally:
        registry.close()


def test_a_long_preset_value_is_not_echoed_at_length(client: httpx.Client) -> None:
    """QA session 36 re-test: a 200,000-character preset came back in full in the 400."""
    r = client.post("/scans", data={"preset": "q" * 200_000}, files={"scan": ("q.png", _png(1))})
    _problem(r, 400)
    assert len(r.content) < 2_000 and "200,000 characters" in r.text
    long_path = client.get("/maps/" + "q" * 30_000)
    assert long_path.status_code in (404, 414, 422) and len(long_path.content) < 2_000
