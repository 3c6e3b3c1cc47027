"""The checked-in OpenAPI document matches the app, and documents both scan encodings."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _render() -> str:
    spec = importlib.util.spec_from_file_location("export_openapi", ROOT / "scripts" / "export_openapi.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.render()


def test_openapi_json_is_current() -> None:
    current = _render()
    stored = (ROOT / "openapi" / "openapi.json").read_text()
    assert stored == current, "openapi/openapi.json is stale: run `python scripts/export_openapi.py`"


def test_openapi_documents_endpoints_and_encodings() -> None:
    doc = json.loads(_render())
    paths = doc["paths"]
    assert {"/healthz", "/readyz", "/metrics", "/maps", "/maps/{map_id}", "/maps/{map_id}/retrieve", "/scans",
            "/localize"} <= set(paths)
    body = paths["/localize"]["post"]["requestBody"]["content"]
    assert {"application/json", "multipart/form-data"} <= set(body)
    assert body["multipart/form-data"]["schema"]["required"] == ["scan", "map_id"]
    assert "delete" in paths["/maps/{map_id}"] and "post" in paths["/maps"]
    pose = doc["components"]["schemas"]["Pose2D"]["properties"]
    assert set(pose) == {"x_m", "y_m", "yaw_deg"}
    ops = [op["operationId"] for p in paths.values() for op in p.values()]
    assert len(ops) == len(set(ops))
