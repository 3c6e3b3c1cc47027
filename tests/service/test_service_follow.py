"""`reradar localize --follow SEQUENCE_DIR`: a drive replayed through one tracking session against a live
server (fake extractor): the table, the summary and the trajectory PNG."""

from __future__ import annotations

import sys
from pathlib import Path

import httpx
import typer
from typer.testing import CliRunner

from reradar_core.io.datasets import write_sequence_poses, write_sequence_scan
from reradar_core.io.poses import PoseSequence
from service.cli import register

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import API_KEY, N_KEYFRAMES, keyframe_poses, keyframe_time, make_scan  # noqa: E402


def test_follow_replays_a_drive_in_tracking_mode(server: tuple[str, Path], fake_map: Path, tmp_path: Path) -> None:
    url, _ = server
    with fake_map.open("rb") as fh:
        r = httpx.post(f"{url}/maps", data={"map_id": "follow-map"}, files={"map_file": ("m.h5", fh)},
                       headers={"X-API-Key": API_KEY})
    assert r.status_code == 201, r.text
    seq = tmp_path / "drive"
    poses = keyframe_poses()  # the drive passes every keyframe of the fake map, in order
    times = [keyframe_time(i) + 10_000_000 for i in range(N_KEYFRAMES)]
    for i, t in enumerate(times):
        write_sequence_scan(seq, "boreas", make_scan(i, t))
    # the fake keyframes are 40 m apart per 0.25 s: give the drive its poses at the scans' mid-sweep times
    # (first azimuth + 124688 us, docs/CONVENTIONS.md), where the service's answers refer to
    write_sequence_poses(seq, "boreas", PoseSequence([t + 124_688 for t in times], poses[:, :2], poses[:, 2]))
    app = typer.Typer()
    register(app)
    png = tmp_path / "follow.png"
    # the folder does not name its radar (no simulator record): a Boreas folder's replay names it
    res = CliRunner().invoke(app, ["localize", "--follow", str(seq), "--server", url, "--map", "follow-map",
                                   "--preset", "boreas", "--out", str(png), "--odometry-noise", "0.01"])
    assert res.exit_code == 0, res.output
    rows = [ln for ln in res.output.splitlines() if ln[:4].strip().isdigit()]
    assert len(rows) == N_KEYFRAMES
    # 40 m between scans: the odometry prior's sigma (0.5 m + 10 % of 40 m) is more than the registration reaches,
    # so every scan is localized globally (docs/SERVICE.md, "Tracking mode")
    assert all(r.split()[2] == "global" for r in rows)
    assert f"success (< 20 m and < 10 deg): {N_KEYFRAMES}/{N_KEYFRAMES}" in res.output
    assert "localized at a wrong pose: 0/" in res.output
    assert f"pose accuracy (<= 2 m and <= 2 deg): {N_KEYFRAMES}/{N_KEYFRAMES} (100.0 %); localized outside it: 0/" \
        in res.output
    assert png.is_file() and png.stat().st_size > 10_000
    bad = CliRunner().invoke(app, ["localize", "--server", url])
    assert bad.exit_code == 2 and "SCAN" in bad.output
