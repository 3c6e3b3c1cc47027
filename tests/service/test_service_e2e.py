"""End to end with the real default DescriptorExtractor and real simulated scans, over HTTP on localhost:
register the shipped demo map, upload a scan, retrieve, localize, and compare with the simulator's ground
truth at the paper's success thresholds (20 m, 10 degrees)."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from maps.paths import DEMO_MAP_PATH, DEMO_QUERIES_DIR
from reradar_core.evaluation import localization_success, radius_for
from service.core.config import Settings
from service.demo import (
    QUERIES_CSV,
    QueryTruth,
    read_queries_csv,
    serve_in_thread,
)

KEY = "e2e-key-0123456789abcdef"


@pytest.fixture(scope="module")
def real_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    settings = Settings(maps_dir=tmp_path_factory.mktemp("maps-e2e"), load_demo_map=False, api_key=KEY,
                        torch_threads=2)
    with serve_in_thread(settings) as url:  # extractor=None: the shipped default model
        yield url


@pytest.fixture(scope="module")
def queries() -> list[QueryTruth]:
    rows = read_queries_csv(DEMO_QUERIES_DIR / QUERIES_CSV)
    assert len(rows) >= 5
    return rows


def _errors(pose: dict, q: QueryTruth) -> tuple[float, float]:
    et = math.hypot(pose["x_m"] - q.x_m, pose["y_m"] - q.y_m)
    er = abs((pose["yaw_deg"] - q.yaw_deg + 180.0) % 360.0 - 180.0)
    return et, er


def test_register_upload_retrieve_localize_real_model(real_server: str, queries: list[QueryTruth]) -> None:
    with httpx.Client(base_url=real_server, timeout=120) as c:
        ready = c.get("/readyz").json()
        assert ready["status"] == "ready" and ready["maps_ready"] == 0
        with DEMO_MAP_PATH.open("rb") as fh:
            r = c.post("/maps", data={"map_id": "demo-route"}, files={"map_file": ("demo.h5", fh)},
                       headers={"X-API-Key": KEY})
        assert r.status_code == 201, f"demo map refused (rebuild it with scripts/build_demo_map.py?): {r.text}"
        assert r.json()["model_id"] == ready["model_id"]

        q = queries[len(queries) // 2]
        up = c.post("/scans", files={"scan": (q.file, (DEMO_QUERIES_DIR / q.file).read_bytes(), "image/png")})
        assert up.status_code == 201, up.text
        scan = up.json()
        assert scan["timestamp_us"] == q.timestamp_us and scan["num_keypoints"] > 0
        retr = c.post("/maps/demo-route/retrieve", json={"scan_id": scan["scan_id"], "top_k": 5}).json()
        assert len(retr["keyframes"]) == 5
        by_ref = c.post("/localize", json={"map_id": "demo-route", "scan_id": scan["scan_id"]}).json()
        inline = c.post("/localize", data={"map_id": "demo-route"},
                        files={"scan": (q.file, (DEMO_QUERIES_DIR / q.file).read_bytes(), "image/png")}).json()
        # the cached features and an inline upload of the same scan give the same answer
        assert by_ref["status"] == inline["status"] and by_ref["num_inliers"] == inline["num_inliers"]

        # A pose claimed as localized must be right (SR thresholds); not_localized is an honest answer (the
        # demo's printout shows which queries are refused and why); the floor of half the queries catches a
        # regression of the pose path.
        wrong, localized = [], 0
        for q in queries:
            files = {"scan": (q.file, (DEMO_QUERIES_DIR / q.file).read_bytes(), "image/png")}
            res = c.post("/localize", data={"map_id": "demo-route"}, files=files).json()
            if res["status"] != "localized":
                # an honest refusal: too little aligns, the pose is ambiguous or the confidence is under the bar
                assert res["reason"] in ("too_few_inliers", "too_few_matches", "no_candidate", "ambiguous",
                                         "low_confidence")
                continue
            et, er = _errors(res["pose"], q)
            if localization_success(et, er, radius_for("boreas")):
                localized += 1
            else:
                wrong.append((q.file, f"{et:.1f} m", f"{er:.1f} deg"))
        assert not wrong, f"queries localized at a wrong pose: {wrong}"
        assert localized >= len(queries) // 2, f"only {localized}/{len(queries)} demo queries localized"


def test_demo_map_fits_the_size_budget() -> None:
    total = sum(p.stat().st_size for p in DEMO_MAP_PATH.parent.rglob("*") if p.is_file())
    assert total <= 20 * 2**20, f"maps/demo is {total / 2**20:.1f} MiB"
    assert Path(DEMO_QUERIES_DIR / QUERIES_CSV).is_file()
