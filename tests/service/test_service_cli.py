"""`reradar localize --server URL SCAN.png` against a live server (fake extractor)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import httpx
import pytest
import typer
from typer.testing import CliRunner

from reradar_core.io.scan import encode_navtech_png_bytes
from service.cli import register

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import API_KEY, keyframe_poses, make_scan  # noqa: E402


@pytest.fixture(scope="module")
def app_and_url(server: tuple[str, Path], fake_map: Path) -> tuple[typer.Typer, str]:
    url, _ = server
    with fake_map.open("rb") as fh:
        r = httpx.post(f"{url}/maps", data={"map_id": "cli-map"}, files={"map_file": ("m.h5", fh)},
                       headers={"X-API-Key": API_KEY})
    assert r.status_code == 201, r.text
    app = typer.Typer()
    register(app)
    return app, url


def test_localize_command_prints_map_pose(app_and_url: tuple[typer.Typer, str], tmp_path: Path) -> None:
    app, url = app_and_url
    scan = tmp_path / "q.png"
    scan.write_bytes(encode_navtech_png_bytes(make_scan(2, 0)))
    res = CliRunner().invoke(app, ["localize", str(scan), "--server", url, "--map", "cli-map"])
    assert res.exit_code == 0, res.output
    x, y, _ = keyframe_poses()[2]
    assert res.output.startswith("localized: ") and f"x={x:.2f} m" in res.output and f"y={y:.2f} m" in res.output
    res = CliRunner().invoke(app, ["localize", str(scan), "--server", url, "--map", "cli-map", "--json"])
    assert json.loads(res.output)["keyframe"]["keyframe_id"] == 2


def test_localize_command_errors(app_and_url: tuple[typer.Typer, str], tmp_path: Path) -> None:
    app, url = app_and_url
    unknown = tmp_path / "u.png"
    unknown.write_bytes(encode_navtech_png_bytes(make_scan(12345, 0)))
    res = CliRunner().invoke(app, ["localize", str(unknown), "--server", url, "--map", "cli-map"])
    assert res.exit_code == 1 and "not localized" in res.output
    res = CliRunner().invoke(app, ["localize", str(unknown), "--server", url, "--map", "nope"])
    assert res.exit_code == 2 and "unknown map" in res.output
    res = CliRunner().invoke(app, ["localize", str(unknown), "--server", "http://127.0.0.1:9", "--map", "x"])
    assert res.exit_code == 3 and "cannot reach" in res.output


def test_localize_command_sends_the_api_key(tmp_path: Path, fake_map: Path) -> None:
    """QA (session 21): `reradar localize` had no way to send X-API-Key, so it failed (401) against any server
    with vehicle keys or beyond loopback. `--api-key` / RERADAR_CLIENT_API_KEY now send one."""
    from service_test_fakes import FakeExtractor

    from service.core.config import Settings
    from service.demo import serve_in_thread

    vehicle = "vehicle-key-for-the-cli-0123"
    settings = Settings(maps_dir=tmp_path / "maps", load_demo_map=False, api_key=API_KEY, vehicle_keys=vehicle,
                        torch_threads=1)
    scan = tmp_path / "q.png"
    scan.write_bytes(encode_navtech_png_bytes(make_scan(2, 0)))
    app = typer.Typer()
    register(app)
    with serve_in_thread(settings, FakeExtractor()) as url:
        with fake_map.open("rb") as fh:
            r = httpx.post(f"{url}/maps", data={"map_id": "keyed"}, files={"map_file": ("m.h5", fh)},
                           headers={"X-API-Key": API_KEY})
        assert r.status_code == 201, r.text
        base = ["localize", str(scan), "--server", url, "--map", "keyed"]
        res = CliRunner().invoke(app, base, env={"RERADAR_CLIENT_API_KEY": ""})
        assert res.exit_code == 2 and "401" in res.output and "--api-key or RERADAR_CLIENT_API_KEY" in res.output
        res = CliRunner().invoke(app, [*base, "--api-key", vehicle])
        assert res.exit_code == 0 and res.output.startswith("localized: "), res.output
        res = CliRunner().invoke(app, base, env={"RERADAR_CLIENT_API_KEY": vehicle})
        assert res.exit_code == 0 and res.output.startswith("localized: "), res.output


def test_localize_command_says_when_the_far_view_answered(app_and_url: tuple[typer.Typer, str], tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """QA session 34: an answer of the map's far view printed like any other; only --json showed `view`."""
    from service.client import ReRadarClient

    app, url = app_and_url
    scan = tmp_path / "q.png"
    scan.write_bytes(encode_navtech_png_bytes(make_scan(2, 0)))
    real = ReRadarClient.localize

    def as_far(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        return real(self, *args, **kwargs).model_copy(update={"view": "far"})

    res = CliRunner().invoke(app, ["localize", str(scan), "--server", url, "--map", "cli-map"])
    assert res.exit_code == 0 and "far view" not in res.output, res.output
    monkeypatch.setattr(ReRadarClient, "localize", as_far)
    res = CliRunner().invoke(app, ["localize", str(scan), "--server", url, "--map", "cli-map"])
    assert res.exit_code == 0 and res.output.startswith("localized: ") and ", far view," in res.output, res.output

    def as_dense(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        return real(self, *args, **kwargs).model_copy(update={"view": "far", "registration": "dense",
                                                               "num_inliers": 0, "confidence": 0.97})

    monkeypatch.setattr(ReRadarClient, "localize", as_dense)  # session 39: no landmark count for a dense answer
    res = CliRunner().invoke(app, ["localize", str(scan), "--server", url, "--map", "cli-map"])
    assert res.exit_code == 0 and "far view, dense registration, confidence 0.97" in res.output, res.output
    assert "inliers" not in res.output
    monkeypatch.setattr(ReRadarClient, "localize", as_far)
    unknown = tmp_path / "u.png"
    unknown.write_bytes(encode_navtech_png_bytes(make_scan(12345, 0)))
    res = CliRunner().invoke(app, ["localize", str(unknown), "--server", url, "--map", "cli-map"])
    assert res.exit_code == 1 and "the far view refused it too" in res.output, res.output
