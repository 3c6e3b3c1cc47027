"""POST /maps checks the uploaded pose file's clock against the scans' (``localization.pose_clock``) at the pose
file's own rate: an archive of scans 2 s apart (a thinned drive) cut each corner's turn between keyframes short
enough that the check, reading the keyframe poses alone, missed a pose file 1 s off (``benchmarks/pose_clock_check.py
--keyframes-only``: boreas-sim's snow drives, +-0.5 and +-1 s not found)."""

from __future__ import annotations

import io
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
from fastapi.testclient import TestClient
from pydantic import SecretStr

from reradar_core.io.scan import RadarScan, encode_navtech_png_bytes
from reradar_core.localization.pose_clock import consecutive_registrations, pose_clock_offset
from reradar_core.matching import AlignmentConfig
from service.core.config import Settings
from service.main import create_app

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from service_test_fakes import API_KEY  # noqa: E402
from world_fakes import WorldExtractor  # noqa: E402

AUTH = {"X-API-Key": API_KEY}
T0 = 1_600_000_000_000_000
HALF_SWEEP_US = 125_000  # poses are taken at mid-sweep (a 4 Hz sweep)


def _slalom(t_s: np.ndarray) -> np.ndarray:
    """(N, 3) poses of a 5 m/s slalom (heading +-15 degrees, a 12 s period) at times ``t_s`` from its start, inside
    ``WorldExtractor``'s world (x from -230 m)."""
    fine = np.arange(0.0, float(t_s.max()) + 1.0, 0.01)
    yaw = np.radians(15.0) * np.sin(2 * np.pi * fine / 12.0)
    x = np.cumsum(5.0 * np.cos(yaw)) * 0.01 - 230.0
    y = np.cumsum(5.0 * np.sin(yaw)) * 0.01
    return np.column_stack([np.interp(t_s, fine, v) for v in (x, y, yaw)])


def _upload(scan_times_us: np.ndarray, pose_shift_s: float) -> tuple[bytes, bytes]:
    """An archive of blank scans at ``scan_times_us`` and a 4 Hz t_us,x,y,yaw pose file whose times run
    ``pose_shift_s`` behind the scans' clock (each row carries the pose of ``pose_shift_s`` later)."""
    buf = io.BytesIO()
    blank = np.zeros((400, 3360), np.float32)
    with zipfile.ZipFile(buf, "w") as zf:
        for t in scan_times_us:
            zf.writestr(f"{t}.png", encode_navtech_png_bytes(RadarScan.from_power(blank, "boreas", start_time_us=int(t))))
    rows_t = T0 + np.arange(-8, 4 * 100) * 250_000
    poses = _slalom((rows_t - T0) / 1e6 + 10.0 + pose_shift_s)
    lines = [f"{t},{p[0]:.4f},{p[1]:.4f},{p[2]:.6f}" for t, p in zip(rows_t, poses, strict=True)]
    return buf.getvalue(), ("t_us,x,y,yaw\n" + "\n".join(lines) + "\n").encode()


def _build(client: TestClient, map_id: str, archive: bytes, poses: bytes) -> dict:
    r = client.post("/maps", data={"map_id": map_id, "preset": "boreas"}, headers=AUTH,
                    files={"archive": ("drive.zip", archive), "poses": ("poses.csv", poses)})
    assert r.status_code == 202, r.text
    deadline = time.monotonic() + 60.0
    while (info := client.get(f"/maps/{map_id}", headers=AUTH).json())["state"] == "building":
        assert time.monotonic() < deadline
        time.sleep(0.05)
    return info


def test_a_pose_file_off_the_scans_clock_is_found_between_keyframes_2_s_apart(tmp_path: Path) -> None:
    scan_times = T0 + np.arange(0, 90, 2) * 1_000_000  # 45 scans, 2 s apart, over 88 s
    # what the radar saw: the slalom at each scan's mid-sweep time
    truth = _slalom((scan_times + HALF_SWEEP_US - T0) / 1e6 + 10.0)
    ext = WorldExtractor({int(t): p for t, p in zip(scan_times, truth, strict=True)})
    cfg = Settings(maps_dir=tmp_path / "maps", load_demo_map=False, api_key=SecretStr(API_KEY), torch_threads=1)
    with TestClient(create_app(cfg, ext)) as client:
        assert _build(client, "on-clock", *_upload(scan_times, 0.0))["state"] == "ready"
        for shift_s, map_id in ((0.5, "half-second-off"), (-1.0, "second-off")):
            failed = _build(client, map_id, *_upload(scan_times, shift_s))
            assert failed["state"] == "failed", failed
            assert failed["error"].startswith(
                f"the keyframe poses are {abs(shift_s):.2f} s {'behind' if shift_s > 0 else 'ahead of'} the scans' "
                "clock: "), failed["error"]
            assert failed["error"].endswith(f"add {shift_s:+.2f} s to its times"), failed["error"]
            assert "/tmp" not in failed["error"]

    # the same check on the keyframe poses alone (interpolated between keyframes 2 s apart) misses the 0.5 s
    feats = ext.describe_batch([RadarScan.from_power(np.zeros((400, 3360), np.float32), "boreas",
                                                     start_time_us=int(t)) for t in scan_times])
    T, ratio = consecutive_registrations(feats.__getitem__, len(feats), AlignmentConfig())
    shifted = _slalom((scan_times + HALF_SWEEP_US - T0) / 1e6 + 10.0 + 0.5)
    assert not pose_clock_offset(T, ratio, scan_times, shifted).offset_detected
