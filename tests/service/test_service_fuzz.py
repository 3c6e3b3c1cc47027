"""Property-based fuzzing of the whole API from its own OpenAPI document (schemathesis, in-process ASGI).

Every operation gets positive and negative (schema-violating) requests from a fixed seed; every response must
be no 5xx and conform to the document (status code, content type, body schema, headers), and the other
schemathesis checks must pass. The fake feature extractor keeps it fast; the service code under test is the
real one. A final test asserts the run made at least ``MIN_REQUESTS`` requests.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from schemathesis.checks import CHECKS
from schemathesis.config import SchemathesisConfig

from maps.build import build_map
from service.core.config import Settings
from service.main import create_app

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import API_KEY, FakeExtractor, keyframe_poses, keyframe_time, make_scan  # noqa: E402

SEED = 20261130
EXAMPLES_PER_OPERATION = 350
MIN_REQUESTS = 2000

_maps_dir = Path(tempfile.mkdtemp(prefix="reradar-fuzz-")) / "maps"
_maps_dir.mkdir()
_extractor = FakeExtractor()
build_map(_maps_dir / "route-a.h5", _extractor, lambda i: make_scan(i, keyframe_time(i)), keyframe_poses(),
          radar_preset="boreas", name="route-a", batch_size=4)
service_app = create_app(Settings(maps_dir=_maps_dir, load_demo_map=False, api_key=API_KEY,
                          vehicle_keys="vehicle-key-0123456789", max_upload_mb=2.0, max_map_upload_mb=4.0),
                 _extractor)
_http_requests = [0]


async def app(scope, receive, send):  # type: ignore[no-untyped-def]
    """The service, counting the HTTP requests that reach it (the checks send some of their own)."""
    if scope["type"] == "http":
        _http_requests[0] += 1
    await service_app(scope, receive, send)


# Why some 4xx are "acceptance" here: a schema cannot say "bytes that decode as a Navtech PNG" or "a scan_id
# that was uploaded before", so schema-valid requests rightly get 404 (unknown ids), 409 (id taken), 413 (a
# scan declaring too many pixels), 415 (a lossy image) or 422 (bytes that are not a scan / map file).
_CONFIG = SchemathesisConfig.from_dict({
    "seed": SEED,
    "headers": {"X-API-Key": API_KEY},
    "checks": {
        "positive_data_acceptance": {"expected-statuses": ["2xx", "400", "401", "403", "404", "409", "413", "415",
                                                           "422"]},
    },
})
schema = schemathesis.openapi.from_asgi("/openapi.json", app, config=_CONFIG)
ALL_CHECKS = CHECKS.get_all()  # every built-in check (registered by loading an OpenAPI schema)

_requests: dict[str, int] = {}


@schema.parametrize()
@settings(max_examples=EXAMPLES_PER_OPERATION, deadline=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
def test_api_conforms_and_never_5xx(case: schemathesis.Case) -> None:
    key = f"{case.method} {case.path}"
    _requests[key] = _requests.get(key, 0) + 1
    case.call_and_validate(checks=ALL_CHECKS)


def test_fuzz_run_was_large_enough() -> None:
    if not _requests:
        pytest.skip("run together with test_api_conforms_and_never_5xx")
    total = _http_requests[0] - 1  # minus the request for /openapi.json
    print(f"schemathesis: {total} requests over {len(_requests)} method x path pairs")  # shown with -s
    assert total >= MIN_REQUESTS, f"only {total} fuzzed requests: {_requests}"
    documented = {f"{m.upper()} {p}" for p, ops in service_app.openapi()["paths"].items() for m in ops}
    assert documented <= set(_requests), f"operations not fuzzed: {documented - set(_requests)}"
    assert len(ALL_CHECKS) >= 14, [c.__name__ for c in ALL_CHECKS]
