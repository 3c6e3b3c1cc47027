"""The README demo: serve the shipped demo map on a real uvicorn server on localhost, localize the demo query
scans over HTTP with the client, print each pose with its ground truth and errors, then stop the server."""

from __future__ import annotations

import contextlib
import csv
import logging
import math
import secrets
import socket
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import uvicorn
from pydantic import SecretStr

from maps.paths import DEMO_MAP_PATH, DEMO_QUERIES_DIR
from maps.store import read_metadata
from reradar_core.evaluation import MAX_ROTATION_ERROR_DEG, localization_success, radius_for
from reradar_core.localization.extractor import FeatureExtractor
from service.client import ReRadarClient
from service.core.config import Settings
from service.core.registry import DEMO_MAP_ID
from service.follow import answer_errors

__all__ = ["QueryTruth", "read_queries_csv", "write_queries_csv", "serve_in_thread", "run_demo"]

QUERIES_CSV = "queries.csv"


@dataclass(frozen=True)
class QueryTruth:
    """A demo query scan and its ground-truth map pose (metres, degrees)."""

    file: str
    timestamp_us: int
    x_m: float
    y_m: float
    yaw_deg: float


def read_queries_csv(path: str | Path) -> list[QueryTruth]:
    """Read ``queries.csv``: columns ``file,timestamp_us,x_m,y_m,yaw_deg`` (the scan's timestamp, its first
    azimuth; the ground-truth map pose at mid-sweep, the instant answers refer to)."""
    with Path(path).open(newline="") as fh:
        return [QueryTruth(r["file"], int(r["timestamp_us"]), float(r["x_m"]), float(r["y_m"]), float(r["yaw_deg"]))
                for r in csv.DictReader(fh)]


def write_queries_csv(path: str | Path, rows: list[QueryTruth]) -> Path:
    path = Path(path)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["file", "timestamp_us", "x_m", "y_m", "yaw_deg"])
        for r in rows:
            w.writerow([r.file, r.timestamp_us, f"{r.x_m:.4f}", f"{r.y_m:.4f}", f"{r.yaw_deg:.4f}"])
    return path


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def serve_in_thread(settings: Settings, extractor: FeatureExtractor | None = None, host: str = "127.0.0.1",
                    ready_timeout_s: float = 300.0, log_level: str = "warning") -> Iterator[str]:
    """Run the service with uvicorn in a background thread on a free loopback port; yields its base URL and
    stops the server on exit."""
    from service.core.http_protocol import HeadTimeoutH11Protocol
    from service.main import create_app

    if host not in ("127.0.0.1", "localhost", "::1"):
        raise ValueError("serve_in_thread only binds loopback addresses")
    app = create_app(settings, extractor)
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind((host, 0))
    port = sock.getsockname()[1]
    HeadTimeoutH11Protocol.header_timeout_s = settings.header_timeout_s
    server = uvicorn.Server(uvicorn.Config(app, log_level=log_level, lifespan="on", access_log=False,
                                           http=HeadTimeoutH11Protocol))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True, name="uvicorn")
    thread.start()
    url = f"http://{host}:{port}"
    try:
        deadline = time.monotonic() + ready_timeout_s
        while not server.started:
            if not thread.is_alive():
                raise RuntimeError("the server stopped during startup (see the log above)")
            if time.monotonic() > deadline:
                raise TimeoutError(f"server did not start within {ready_timeout_s:.0f} s")
            time.sleep(0.05)
        yield url
    finally:
        server.should_exit = True
        thread.join(timeout=30)
        sock.close()


def run_demo(map_path: Path = DEMO_MAP_PATH, queries_dir: Path = DEMO_QUERIES_DIR,
             echo: Callable[[str], None] = print, threads: int = 1) -> int:
    """Serve ``map_path`` as map ``demo``, localize every query in ``queries_dir/queries.csv`` over HTTP and
    print the results.

    Returns 0 when the run completed and no query was reported ``localized`` at a wrong pose (beyond the SR
    thresholds): ``not_localized`` is an honest answer and is counted in the printed success rate, a wrong
    pose claimed as localized is a failure (exit 1). 2 when the demo map is missing."""
    if not map_path.is_file():
        echo(f"error: demo map {map_path} not found; build it with `python scripts/build_demo_map.py`")
        return 2
    truth = read_queries_csv(queries_dir / QUERIES_CSV)
    # the paper's success rule (Sec. "Evaluation Metrics"): e_t < R of the map's radar (20 m Boreas), e_r < 10 deg
    radius_m = radius_for(read_metadata(map_path).radar_preset)
    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line per request would bury the table
    with tempfile.TemporaryDirectory(prefix="reradar-demo-") as tmp:
        maps_dir = Path(tmp) / "maps"
        maps_dir.mkdir()
        (maps_dir / f"{DEMO_MAP_ID}.h5").write_bytes(map_path.read_bytes())
        # a throw-away operator key: the demo registers nothing, and a generated one would be logged
        settings = Settings(maps_dir=maps_dir, load_demo_map=False, torch_threads=threads,  # model: RERADAR_MODEL
                            api_key=SecretStr(secrets.token_urlsafe(24)))
        echo("starting the ReRadar service (uvicorn, loopback) on the demo map ...")
        t_start = time.perf_counter()
        with serve_in_thread(settings) as url, ReRadarClient(url) as client:
            ready = client.wait_ready()
            info = client.get_map(DEMO_MAP_ID)
            echo(f"service ready at {url} in {time.perf_counter() - t_start:.1f} s: model {ready.model_id}, "
                 f"map '{info.id}' with {info.num_keyframes} keyframes ({info.index_kind} index)")
            echo("")
            head = (f"{'query':<22} {'status':<13} {'x_m':>8} {'y_m':>8} {'yaw_deg':>8} | {'gt_x_m':>8} "
                    f"{'gt_y_m':>8} {'gt_yaw':>8} | {'err_m':>6} {'err_deg':>7} {'inl':>4} {'conf':>5} {'ms':>6}")
            echo(head)
            echo("-" * len(head))
            errs_t, errs_r, lat, ok, wrong = [], [], [], 0, 0
            for q in truth:
                t0 = time.perf_counter()
                res = client.localize(DEMO_MAP_ID, scan_path=queries_dir / q.file)
                ms = (time.perf_counter() - t0) * 1e3
                lat.append(ms)
                if res.status == "localized" and res.pose is not None:
                    et, er = answer_errors(res.pose, (q.x_m, q.y_m, math.radians(q.yaw_deg)))
                    success = bool(localization_success(et, er, radius_m))
                    ok += success
                    wrong += not success
                    if success:
                        errs_t.append(et)
                        errs_r.append(er)
                    echo(f"{q.file:<22} {res.status:<13} {res.pose.x_m:8.2f} {res.pose.y_m:8.2f} "
                         f"{res.pose.yaw_deg:8.2f} | {q.x_m:8.2f} {q.y_m:8.2f} {q.yaw_deg:8.2f} | {et:6.2f} "
                         f"{er:7.2f} {res.num_inliers:4d} {res.confidence:5.2f} {ms:6.0f}")
                else:
                    echo(f"{q.file:<22} {res.status:<13} {'-':>8} {'-':>8} {'-':>8} | {q.x_m:8.2f} {q.y_m:8.2f} "
                         f"{q.yaw_deg:8.2f} | {'-':>6} {'-':>7} {res.num_inliers:4d} {res.confidence:5.2f} {ms:6.0f}  "
                         f"({res.reason})")
            echo("")
            n = len(truth)
            mean_t = f"{np.mean(errs_t):.2f} m" if errs_t else "n/a"
            mean_r = f"{np.mean(errs_r):.2f} deg" if errs_r else "n/a"
            echo(f"success (< {radius_m:g} m and < {MAX_ROTATION_ERROR_DEG:g} deg): {ok}/{n} "
                 f"({100.0 * ok / max(n, 1):.0f}%); mean error over successes: {mean_t}, {mean_r}; "
                 f"latency per POST /localize (inline PNG, client side): p50 {np.percentile(lat, 50):.0f} ms, "
                 f"max {np.max(lat):.0f} ms")
            echo(f"not localized: {n - ok - wrong}/{n}; localized at a wrong pose: {wrong}/{n}")
        echo("server stopped.")
    return 0 if wrong == 0 else 1
