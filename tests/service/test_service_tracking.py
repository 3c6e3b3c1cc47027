"""Tracking mode over HTTP: a session's second scan is registered from its first pose plus odometry; an
explicit prior works without a session; inconsistent or partial tracking fields are refused with 400."""

from __future__ import annotations

import sys
from pathlib import Path

import httpx
import numpy as np
import pytest

from reradar_core.geometry.se2 import relative_pose
from reradar_core.io.scan import encode_navtech_png_bytes

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import (  # noqa: E402
    API_KEY,
    keyframe_poses,
    keyframe_time,
    make_scan,
    register_map_file,
    started_app,
    upload_map_file,
)


@pytest.fixture(scope="module")
def client(server: tuple[str, Path], fake_map: Path) -> httpx.Client:
    url, _ = server
    with httpx.Client(base_url=url, timeout=60) as c:
        register_map_file(c, fake_map, "route-t")
        yield c


def _localize(c: httpx.Client, seed: int, **fields: object) -> httpx.Response:
    files = {"scan": ("q.png", encode_navtech_png_bytes(make_scan(seed, 0)), "image/png")}
    return c.post("/localize", data={"map_id": "route-t", **{k: str(v) for k, v in fields.items()}}, files=files)


def test_session_tracks_from_previous_pose_and_odometry(client: httpx.Client) -> None:
    poses = keyframe_poses()
    first = _localize(client, 2, session_id="veh-1").json()
    assert first["status"] == "localized" and first["mode"] == "global" and first["session_id"] == "veh-1"
    assert first["keyframe"]["keyframe_id"] == 2 and first["alignment_score"] >= 0.5
    odo = relative_pose(poses[2], poses[3])  # the vehicle drove from keyframe 2 to keyframe 3
    # 40 m of odometry: sigma 0.5 + 10 % = 4.5 m, more than the registration reaches (TrackingConfig.covers)
    far = _localize(client, 3, session_id="veh-1", odom_dx_m=odo[0], odom_dy_m=odo[1],
                    odom_dyaw_deg=float(odo[2]) * 180 / 3.141592653589793).json()
    assert far["status"] == "localized" and far["mode"] == "global" and not far["tracking_lost"]
    assert far["keyframe"]["keyframe_id"] == 3
    # the vehicle creeps 0.2 m on: tracked from that answer plus the odometry
    odo = relative_pose(poses[3], poses[3] + [0.2 * np.cos(poses[3, 2]), 0.2 * np.sin(poses[3, 2]), 0.0])
    second = _localize(client, 3, session_id="veh-1", odom_dx_m=odo[0], odom_dy_m=odo[1],
                       odom_dyaw_deg=0.0).json()
    assert second["status"] == "localized" and second["mode"] == "tracking" and not second["tracking_lost"]
    assert second["keyframe"]["keyframe_id"] == 3
    assert second["pose"]["x_m"] == pytest.approx(poses[3, 0], abs=0.3)
    assert second["pose"]["y_m"] == pytest.approx(poses[3, 1], abs=0.3)
    assert "track_ms" in second["timings_ms"] and "screen_ms" not in second["timings_ms"]
    lost = _localize(client, 999, session_id="veh-1", odom_dx_m=1.0, odom_dy_m=0.0, odom_dyaw_deg=0.0).json()
    assert lost["status"] == "not_localized" and lost["tracking_lost"] and lost["mode"] == "global"
    other = _localize(client, 3, session_id="veh-2").json()  # a new session starts global
    assert other["mode"] == "global" and other["status"] == "localized"


def test_explicit_prior_and_refused_partial_fields(client: httpx.Client) -> None:
    poses = keyframe_poses()
    res = _localize(client, 1, prior_x_m=poses[1, 0] + 1.0, prior_y_m=poses[1, 1] - 1.0,
                    prior_yaw_deg=float(poses[1, 2]) * 180 / 3.141592653589793 + 2.0, prior_sigma_m=2.0).json()
    assert res["mode"] == "tracking" and res["status"] == "localized" and res["keyframe"]["keyframe_id"] == 1
    assert res["pose"]["x_m"] == pytest.approx(poses[1, 0], abs=0.3)
    # a prior far from where the scan really is: no consistent pose near it, so the global answer is used
    far = _localize(client, 1, prior_x_m=poses[4, 0], prior_y_m=poses[4, 1], prior_yaw_deg=0.0).json()
    assert far["mode"] == "global" and far["tracking_lost"] and far["keyframe"]["keyframe_id"] == 1
    for bad in ({"odom_dx_m": 1.0}, {"prior_x_m": 1.0, "prior_y_m": 2.0}, {"prior_sigma_m": 1.0},
                {"session_id": "no spaces allowed"}):
        r = _localize(client, 1, **bad)
        assert r.status_code in (400, 422), (bad, r.status_code)
        assert "detail" in r.json()


def test_odometry_needs_a_session_and_a_turn_is_read_modulo_360(client: httpx.Client) -> None:
    """QA (session 23): odometry without a ``session_id`` was dropped without a word (200, global); and a turn sent
    as 342.8 degrees instead of -17.2 grew the heading sigma by 10 % of 342.8 degrees, so the scan silently went
    global. Now the first is a 400 that says what to send, and every equal turn gives the same prior."""
    r = _localize(client, 3, odom_dx_m=0.2, odom_dy_m=0.0, odom_dyaw_deg=0.0)
    assert r.status_code == 400 and "session_id" in r.json()["detail"]
    poses = keyframe_poses()
    for session, turn in (("veh-w0", 0.0), ("veh-w1", 360.0), ("veh-w2", -360.0)):
        first = _localize(client, 3, session_id=session).json()
        assert first["status"] == "localized" and first["keyframe"]["keyframe_id"] == 3
        odo = relative_pose(poses[3], poses[3] + [0.2 * np.cos(poses[3, 2]), 0.2 * np.sin(poses[3, 2]), 0.0])
        second = _localize(client, 3, session_id=session, odom_dx_m=odo[0], odom_dy_m=odo[1],
                           odom_dyaw_deg=turn).json()
        assert second["mode"] == "tracking" and second["status"] == "localized", (turn, second)
        assert second["pose"]["x_m"] == pytest.approx(poses[3, 0], abs=0.3)


def test_pose_headings_are_reported_in_minus_180_to_180() -> None:
    """QA (session 23): the range of ``yaw_deg`` was not stated, and a keyframe pose stored unwrapped would have
    been reported as it was stored. Every pose is now reported in (-180, 180] degrees, the value ``wrap_angle``
    gives (no numpy or OpenCV in the schema module: the vehicle-side client imports it)."""
    import math

    from reradar_core.geometry.se2 import wrap_angle
    from service.api.schemas import Pose2D

    for yaw in (0.0, math.pi, -math.pi, 3 * math.pi, -3 * math.pi, 2 * math.pi, -3.141593, 3.141593, 7.5, -12.0):
        deg = Pose2D.from_array(np.array([1.0, 2.0, yaw])).yaw_deg
        assert -180.0 < deg <= 180.0
        assert deg == pytest.approx(math.degrees(float(wrap_angle(yaw))), abs=1e-9)
    assert Pose2D.from_array(np.array([0.0, 0.0, -math.pi])).yaw_deg == 180.0


def test_a_sessions_scan_times_give_the_tracked_answer_the_vehicles_motion(
        tmp_path: Path, fake_map: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Session 30: each scan's own time is kept with the session's pose, and the next scan's odometry over the time
    between them is the vehicle's motion that ``Localizer.track`` receives (``PosePrior.twist``) - also when the
    request sends an explicit prior, under the service's motion settings."""
    import math

    from reradar_core.localization import Localizer

    seen: list[object] = []
    real_track = Localizer.track

    def recording(self: Localizer, features: object, prior: object, config: object = None) -> object:
        seen.append(prior)
        return real_track(self, features, prior, config)  # type: ignore[arg-type]

    monkeypatch.setattr(Localizer, "track", recording)
    poses = keyframe_poses()
    step = relative_pose(poses[3], poses[3] + [0.2 * np.cos(poses[3, 2]), 0.2 * np.sin(poses[3, 2]), 0.0])

    def post(c: object, t_us: int, **fields: object) -> dict:
        files = {"scan": ("q.png", encode_navtech_png_bytes(make_scan(3, t_us)), "image/png")}
        r = c.post("/localize", data={"map_id": "route-m", **{k: str(v) for k, v in fields.items()}},  # type: ignore[attr-defined]
                   files=files, headers={"X-API-Key": API_KEY})
        assert r.status_code == 200, r.text
        return r.json()

    odo = {"odom_dx_m": step[0], "odom_dy_m": step[1], "odom_dyaw_deg": 0.0}
    with started_app(tmp_path / "maps") as c:
        assert upload_map_file(c, fake_map, "route-m").status_code in (200, 201, 202)
        t0 = keyframe_time(3)
        assert post(c, t0, session_id="veh")["mode"] == "global"
        tracked = post(c, t0 + 250_000, session_id="veh", **odo)  # 0.2 m in 0.25 s: 0.8 m/s
        assert tracked["mode"] == "tracking"
        prior = seen[-1]
        assert prior.timestamp_us == t0 + 250_000  # type: ignore[attr-defined]
        np.testing.assert_allclose(prior.twist, [0.8, 0.0, 0.0], atol=1e-6)  # type: ignore[attr-defined]
        # an explicit prior in the session keeps the scan's time and the vehicle's motion
        post(c, t0 + 500_000, session_id="veh", prior_x_m=poses[3, 0], prior_y_m=poses[3, 1],
             prior_yaw_deg=math.degrees(poses[3, 2]), **odo)
        prior = seen[-1]
        assert prior.timestamp_us == t0 + 500_000 and prior.twist is not None  # type: ignore[attr-defined]
    with started_app(tmp_path / "maps", localization={"motion": {"max_keyframe_gap_s": 0.1}}) as c:
        post(c, t0, session_id="veh2")
        post(c, t0 + 250_000, session_id="veh2", **odo)  # 0.25 s apart: over this service's 0.1 s
        assert seen[-1].twist is None  # type: ignore[attr-defined]
