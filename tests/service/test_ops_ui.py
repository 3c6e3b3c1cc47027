"""The operator page and the offline API docs, in a real headless browser (Debian's chromium + chromedriver).

The page must draw the map's keyframe trajectory and the latest localization from the live API; the
canvas screenshot is checked for the trajectory's colour along the known keyframe positions.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from reradar_core.io.scan import encode_navtech_png_bytes
from service.core.config import Settings
from service.demo import serve_in_thread

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import (  # noqa: E402
    API_KEY,
    N_KEYFRAMES,
    FakeExtractor,
    keyframe_poses,
    keyframe_time,
    make_scan,
    register_map_file,
)

TRAJ_BGR = (180, 119, 31)  # #1f77b4 in service/ui/app.js, as OpenCV's BGR
OK_BGR = (44, 160, 44)  # #2ca02c


def _browser_paths() -> tuple[str, str]:
    """chromium and chromedriver; installed with apt-get when missing and possible, else skip (outside CI)."""
    found = shutil.which("chromium"), shutil.which("chromedriver")
    if all(found):
        return found  # type: ignore[return-value]
    if os.environ.get("CI"):
        pytest.fail("chromium / chromedriver missing: .ci/run installs them (apt-get install chromium chromium-driver)")
    if hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("apt-get"):
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        subprocess.run(["apt-get", "install", "-y", "-qq", "--no-install-recommends", "chromium", "chromium-driver"],
                       env=env, capture_output=True, timeout=900, check=False)
        found = shutil.which("chromium"), shutil.which("chromedriver")
        if all(found):
            return found  # type: ignore[return-value]
    pytest.skip("no chromium + chromedriver and they cannot be installed here (needs root and apt-get)")


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    chrome, driver_path = _browser_paths()
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = chrome
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--window-size=1400,1000", "--force-device-scale-factor=1"):
        opts.add_argument(arg)
    drv = webdriver.Chrome(service=Service(executable_path=driver_path), options=opts)
    drv.set_page_load_timeout(60)
    try:
        yield drv
    finally:
        drv.quit()


@pytest.fixture(scope="module")
def live(server: tuple[str, Path], fake_map: Path) -> str:
    """The live server with the fake map registered as ``city`` and two localizations on it."""
    url, _ = server
    with httpx.Client(base_url=url, timeout=60) as c:
        register_map_file(c, fake_map, "city")
        for i in (1, 4):
            png = encode_navtech_png_bytes(make_scan(i, keyframe_time(i)))
            r = c.post("/localize", data={"map_id": "city"}, files={"scan": ("q.png", png, "image/png")})
            assert r.status_code == 200 and r.json()["status"] == "localized", r.text
    return url


def _wait(cond, timeout_s: float = 30.0):  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = cond()
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError("condition not met in time")


def test_data_endpoints(live: str) -> None:
    with httpx.Client(base_url=live, timeout=30) as c:
        traj = c.get("/ui/api/maps/city/trajectory").json()
        np.testing.assert_allclose(traj["x_m"], keyframe_poses()[:, 0], atol=1e-3)
        np.testing.assert_allclose(traj["yaw_deg"], np.degrees(keyframe_poses()[:, 2]), atol=0.01)
        fixes = c.get("/ui/api/maps/city/localizations", params={"limit": 10}).json()["data"]
        assert [f["keyframe_id"] for f in fixes] == [4, 1]  # newest first
        assert fixes[0]["status"] == "localized" and fixes[0]["latency_ms"] > 0
        assert abs(fixes[0]["x_m"] - keyframe_poses()[4, 0]) < 1.0 and 0 < fixes[0]["confidence"] <= 1
        assert c.get("/ui/api/maps/nope/trajectory").status_code == 404
        assert c.get("/ui/api/maps/city/localizations", params={"limit": 0}).status_code == 422
        page = c.get("/").text
        assert "<canvas" in page and "http://" not in page and "https://" not in page
        docs = c.get("/docs").text
        assert "/ui/vendor/swagger-ui-bundle.js" in docs and "cdn" not in docs.lower()
        assert c.get("/ui/vendor/swagger-ui-bundle.js").status_code == 200
        assert "cdn" not in c.get("/redoc").text.lower()


def test_operator_page_draws_trajectory_and_localizations(live: str, browser, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    from selenium.webdriver.common.by import By

    browser.get(live + "/")
    canvas = browser.find_element(By.ID, "trajectory")
    _wait(lambda: canvas.get_attribute("data-points") == str(N_KEYFRAMES)
          and canvas.get_attribute("data-fixes") == "2")
    rows = _wait(lambda: browser.find_elements(By.CSS_SELECTOR, "#fixes tbody tr"))
    assert len(rows) == 2 and "localized" in rows[0].text
    map_row = browser.find_element(By.CSS_SELECTOR, "#maps tbody tr")
    assert "city" in map_row.text and "ready" in map_row.text and "100%" in map_row.text

    shot = Path(os.environ.get("RERADAR_UI_SCREENSHOT", tmp_path / "operator.png"))
    canvas.screenshot(str(shot))
    img = cv2.imread(str(shot), cv2.IMREAD_COLOR)
    assert img is not None
    traj = np.all(np.abs(img.astype(int) - TRAJ_BGR) <= 12, axis=2)
    ok = np.all(np.abs(img.astype(int) - OK_BGR) <= 12, axis=2)
    h, w = traj.shape
    ys, xs = np.nonzero(traj)
    # the route runs 200 m east and 15 m south: a long line across most of the canvas width, sloping down
    assert traj.sum() > 500, f"trajectory colour found on only {traj.sum()} pixels"
    assert xs.max() - xs.min() > 0.8 * w
    left, right = ys[xs < xs.min() + 20].mean(), ys[xs > xs.max() - 20].mean()
    assert right > left  # map y decreases eastwards -> lower on screen at the east end
    assert ok.sum() > 50, "no localization marker drawn"
    # each keyframe position (scaled like app.js) is on the drawn line (or under a localization marker)
    poses = keyframe_poses()
    x0, x1, y0, y1 = poses[:, 0].min(), poses[:, 0].max(), poses[:, 1].min(), poses[:, 1].max()
    scale = min((w - 60) / (x1 - x0), (h - 60) / (y1 - y0))
    for x, y in poses[:, :2]:
        px = int(round(w / 2 + (x - (x0 + x1) / 2) * scale))
        py = int(round(h / 2 - (y - (y0 + y1) / 2) * scale))
        near = (traj | ok)[max(py - 3, 0):py + 4, max(px - 3, 0):px + 4]
        assert near.any(), f"keyframe ({x}, {y}) not drawn near pixel ({px}, {py})"


def test_operator_page_sends_the_typed_key_when_vehicle_keys_are_configured(  # type: ignore[no-untyped-def]
        browser, fake_map: Path, tmp_path: Path) -> None:
    """With vehicle keys, the page's data endpoints (where vehicles are) need a key: the page says so, and
    draws once a vehicle key is typed into its key field."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    vehicle = "vehicle-key-0123456789"
    settings = Settings(maps_dir=tmp_path / "maps", load_demo_map=False, api_key=API_KEY, vehicle_keys=vehicle)
    with serve_in_thread(settings, FakeExtractor()) as url, httpx.Client(base_url=url, timeout=60) as c:
        register_map_file(c, fake_map, "keyed")
        png = encode_navtech_png_bytes(make_scan(3, keyframe_time(3)))
        r = c.post("/localize", data={"map_id": "keyed"}, files={"scan": ("q.png", png, "image/png")},
                   headers={"X-API-Key": vehicle})
        assert r.status_code == 200 and r.json()["status"] == "localized", r.text
        browser.get(url + "/")
        status = browser.find_element(By.ID, "service-status")
        _wait(lambda: "HTTP 401" in status.text and "API key" in status.text)
        canvas = browser.find_element(By.ID, "trajectory")
        assert canvas.get_attribute("data-points") == "0"
        key = browser.find_element(By.ID, "api-key")
        key.send_keys(vehicle, Keys.TAB)  # "change" fires when the field loses focus
        _wait(lambda: canvas.get_attribute("data-points") == str(N_KEYFRAMES)
              and canvas.get_attribute("data-fixes") == "1")
        _wait(lambda: status.text.startswith("live"))


def test_swagger_ui_renders_offline(live: str, browser) -> None:  # type: ignore[no-untyped-def]
    from selenium.webdriver.common.by import By

    browser.get(live + "/docs")
    title = _wait(lambda: browser.find_elements(By.CSS_SELECTOR, ".swagger-ui .info .title"))
    assert "ReRadar" in title[0].text
    ops = _wait(lambda: browser.find_elements(By.CSS_SELECTOR, ".opblock-summary-path"))
    assert any("/localize" in o.text for o in ops)
