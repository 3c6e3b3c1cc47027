"""Operations plumbing: BLAS thread limits (threadpoolctl), JSON log lines, faiss' loader kept quiet."""

from __future__ import annotations

import io
import json
import logging
import subprocess
import sys

import pytest

from service.core.blas import limit_blas_threads
from service.core.logs import JsonFormatter, configure_logging


def test_limit_blas_threads_sets_every_loaded_blas() -> None:
    import scipy.linalg  # noqa: F401 - loads scipy's own OpenBLAS next to numpy's
    from threadpoolctl import threadpool_info

    assert limit_blas_threads(1)
    blas = [i for i in threadpool_info() if i["user_api"] == "blas"]
    assert len(blas) >= 2 and all(i["num_threads"] == 1 for i in blas)


def test_json_formatter_one_object_per_line_with_extras_and_traceback() -> None:
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.setFormatter(JsonFormatter())
    log = logging.getLogger("reradar.test_ops")
    log.addHandler(handler)
    log.propagate = False
    try:
        log.warning("map %s loaded", "demo", extra={"map_id": "demo", "keyframes": 20})
        try:
            raise ValueError("boom")
        except ValueError:
            log.exception("failed\nwith a newline")
    finally:
        log.removeHandler(handler)
    lines = stream.getvalue().splitlines()
    assert len(lines) == 2  # the newline in the message and the traceback stay inside one JSON line
    first, second = (json.loads(line) for line in lines)
    assert first["msg"] == "map demo loaded" and first["level"] == "WARNING" and first["keyframes"] == 20
    assert first["logger"] == "reradar.test_ops" and first["ts"].endswith("Z")
    assert second["msg"] == "failed\nwith a newline" and "ValueError: boom" in second["exc"]


def test_uvicorn_access_line_is_structured() -> None:
    record = logging.LogRecord("uvicorn.access", logging.INFO, __file__, 1, '%s - "%s %s HTTP/%s" %d',
                               ("127.0.0.1:5000", "GET", "/maps", "1.1", 200), None)
    doc = json.loads(JsonFormatter().format(record))
    assert (doc["method"], doc["path"], doc["status"]) == ("GET", "/maps", 200)


def test_service_start_logs_json_and_no_faiss_probe_lines() -> None:
    """A fresh interpreter that configures logging like the CLI, then imports the app (which imports faiss)."""
    code = (
        "import logging; logging.basicConfig(level=logging.INFO)\n"
        "import service.main\n"
        "from service.core.logs import configure_logging\n"
        "configure_logging('INFO', 'json')\n"
        "logging.getLogger('service').info('started')\n"
        "logging.getLogger('uvicorn.error').info('uvicorn line')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert "faiss" not in out.stderr and "ModuleNotFoundError" not in out.stderr
    lines = [json.loads(line) for line in out.stderr.splitlines()]
    assert [d["msg"] for d in lines] == ["started", "uvicorn line"]


@pytest.fixture
def _restore_root_logging():  # type: ignore[no-untyped-def]
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


@pytest.mark.usefixtures("_restore_root_logging")
def test_configure_logging_replaces_its_own_handler_not_others() -> None:
    root = logging.getLogger()
    other = logging.Handler()
    root.addHandler(other)
    configure_logging("INFO", "json")
    configure_logging("WARNING", "text")
    ours = [h for h in root.handlers if type(h).__name__ == "_OurHandler"]
    assert len(ours) == 1 and other in root.handlers and root.level == logging.WARNING


def test_features_encoding_round_trip_is_exact_and_pickle_free() -> None:
    import numpy as np

    from reradar_core.features import ScanFeatures
    from service.core.shared_state import decode_features, encode_features

    rng = np.random.default_rng(0)
    g = rng.normal(size=256).astype(np.float32)
    f = ScanFeatures(g / np.linalg.norm(g), rng.normal(size=(512, 2)) * 50, rng.normal(size=(512, 16)), 123456789)
    blob = encode_features(f, "boreas")
    assert len(blob) < 24_000  # what docs/OPERATIONS.md sizes Redis with
    back, preset, assumed, far, dense = decode_features(blob)
    assert preset == "boreas" and not assumed and back.timestamp_us == 123456789 and far is None and dense is None
    for name in ("global_descriptor", "keypoints_xy_m", "local_descriptors"):
        a, b = getattr(f, name), getattr(back, name)
        assert a.dtype == b.dtype and np.array_equal(a, b)
    assert decode_features(encode_features(f, None))[1] is None
    with np.load(io.BytesIO(blob), allow_pickle=False) as z:  # loads without pickle
        assert set(z.files) == {"global_descriptor", "keypoints_xy_m", "local_descriptors", "timestamp_us", "preset",
                                "preset_open"}
    # the far view's features (a scan uploaded while a map has a far-view companion) travel with it
    far_f = ScanFeatures(g / np.linalg.norm(g), rng.normal(size=(300, 2)) * 150, rng.normal(size=(300, 16)), 123456789)
    back, _, _, far, _ = decode_features(encode_features(f, "boreas", far_features=far_f))
    assert far is not None and np.array_equal(back.keypoints_xy_m, f.keypoints_xy_m)
    for name in ("global_descriptor", "keypoints_xy_m", "local_descriptors"):
        assert np.array_equal(getattr(far, name), getattr(far_f, name))
    # and its dense image (float16); one that is not a finite square float image is dropped, not trusted
    img = rng.normal(scale=0.01, size=(257, 257)).astype(np.float16)
    *_, dense = decode_features(encode_features(f, "boreas", far_features=far_f, dense_image=img))
    assert dense is not None and dense.dtype == np.float16 and np.array_equal(dense, img)
    for bad in (img[:, :200], np.full((257, 257), np.nan, np.float16), np.zeros((257, 257), np.int8)):
        with np.load(io.BytesIO(encode_features(f, "boreas")), allow_pickle=False) as z:
            fields = {k: z[k] for k in z.files}
        buf = io.BytesIO()
        np.savez(buf, **fields, dense_image=bad)  # as another writer might have stored it
        assert decode_features(buf.getvalue())[4] is None


def test_trajectory_subsample_keeps_ends_and_bound() -> None:
    import numpy as np

    from service.api.routes.ui import trajectory_points

    assert trajectory_points(np.zeros((7, 3)), max_points=10).tolist() == list(range(7))
    idx = trajectory_points(np.zeros((100_001, 3)), max_points=5000)
    assert len(idx) == 5000 and idx[0] == 0 and idx[-1] == 100_000 and np.all(np.diff(idx) > 0)


def test_recent_localizations_in_memory_newest_first_and_bounded() -> None:
    from service.core.shared_state import RecentLocalizations

    recent = RecentLocalizations(capacity=3)
    for i in range(5):
        recent.add("m", {"i": i})
    assert [r["i"] for r in recent.latest("m", 10)] == [4, 3, 2]
    assert recent.latest("m", 1) == [{"i": 4}] and recent.latest("other", 5) == []
    recent.drop("m")
    assert recent.latest("m", 5) == []


def test_build_note_names_a_missing_worker_and_a_silent_one() -> None:
    """Session 21: a build whose only worker died read ``building`` forever with no hint; GET /maps now says why."""
    from service.core.jobs import build_note

    running = {"state": "running", "heartbeat": "1001.0"}
    queued = {"state": "queued", "heartbeat": "0"}
    # a worker beat 3 s ago and the build's own heartbeat is fresh: nothing to say
    assert build_note(running, newest_worker_beat=1000.0, now=1003.0, stale_after_s=15) is None
    assert build_note(queued, newest_worker_beat=1000.0, now=1003.0, stale_after_s=15) is None
    # no worker ever, or none for longer than the stale time: the note says what to start
    for beat in (None, 980.0):
        note = build_note(queued, newest_worker_beat=beat, now=1000.0, stale_after_s=15)
        assert note is not None and "reradar worker" in note and "15 s" in note
    # workers are alive, but the one on this build went silent (about to be retried)
    note = build_note({"state": "running", "heartbeat": "980.0"}, newest_worker_beat=999.0, now=1000.0,
                      stale_after_s=15)
    assert note is not None and "retry" in note


def test_a_build_with_every_scan_described_says_it_is_in_its_last_pass() -> None:
    """Session 28: after the last scan a build measures the map's place repetition (20-40 ms per keyframe) with
    progress at 100 %; the note says so instead of leaving it to look stuck."""
    from pathlib import Path

    from service.core.registry import MapEntry, last_pass_note

    def entry(state: str, done: int, total: int) -> MapEntry:
        return MapEntry("m", Path("m.h5"), state, scans_done=done, scans_total=total)  # type: ignore[arg-type]

    note = last_pass_note(entry("building", 80, 80))
    assert note is not None and "measuring where the map repeats itself" in note
    assert entry("building", 80, 80).progress == 1.0
    for e in (entry("building", 79, 80), entry("building", 0, 0), entry("ready", 80, 80), entry("failed", 80, 80)):
        assert last_pass_note(e) is None


def test_json_lines_leave_out_uvicorns_coloured_copy() -> None:
    """QA (session 21): uvicorn's start-up lines carried ``color_message`` (the message with terminal escape codes)."""
    record = logging.LogRecord("uvicorn.error", logging.INFO, "", 0, "Uvicorn running on %s", ("http://x",), None)
    record.color_message = "Uvicorn running on \x1b[1m%s\x1b[0m"
    doc = json.loads(JsonFormatter().format(record))
    assert doc["msg"] == "Uvicorn running on http://x" and "color_message" not in doc


def test_trajectory_headings_stay_in_the_api_range_after_rounding() -> None:
    """QA (session 24): a stored yaw of -179.99988 degrees was served as -180.0, outside (-180, 180]."""
    import numpy as np

    from service.api.routes.ui import _wrapped_deg

    got = _wrapped_deg(np.round(np.array([-179.99988, 179.99988, -179.99, 45.25, 0.0]), 2))
    assert got.tolist() == [180.0, 180.0, -179.99, 45.25, 0.0]
