"""Sustained throughput of one service replica: C concurrent clients POST /localize for T seconds.

Starts ``reradar serve`` (real model, shipped demo map) as a separate process on a free loopback port, then
runs C client threads that each send the demo query scans (inline PNG, multipart) back to back. Prints
localizations/s, latency percentiles and the load average, for docs/OPERATIONS.md.

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_throughput.py --clients 1 2 4 --seconds 60
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def run(url: str, scans: list[bytes], clients: int, seconds: float) -> dict[str, float]:
    lat: list[float] = []
    outcomes: dict[str, int] = {}
    lock = threading.Lock()
    stop_at = time.monotonic() + seconds

    def client(k: int) -> None:
        with httpx.Client(base_url=url, timeout=60) as c:
            i = k
            while time.monotonic() < stop_at:
                t0 = time.perf_counter()
                r = c.post("/localize", data={"map_id": "demo"}, files={"scan": ("q.png", scans[i % len(scans)])})
                dt = time.perf_counter() - t0
                key = r.json().get("status", "?") if r.status_code == 200 else f"http_{r.status_code}"
                with lock:
                    lat.append(dt)
                    outcomes[key] = outcomes.get(key, 0) + 1
                i += 1

    t0 = time.monotonic()
    threads = [threading.Thread(target=client, args=(k,)) for k in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.monotonic() - t0
    a = np.array(lat) * 1e3
    return {"clients": clients, "requests": len(a), "per_s": len(a) / wall, "p50_ms": float(np.percentile(a, 50)),
            "p99_ms": float(np.percentile(a, 99)), "errors": sum(v for k, v in outcomes.items() if k.startswith("http_")),
            "localized": outcomes.get("localized", 0)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clients", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--warmup", type=int, default=8, help="requests before measuring")
    args = ap.parse_args()

    queries = sorted((REPO / "maps" / "demo" / "queries").glob("*.png"))
    scans = [q.read_bytes() for q in queries]
    port = _free_port()
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "RERADAR_MAPS_DIR": tmp, "RERADAR_LOAD_DEMO_MAP": "true",
               "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS", "1")}
        proc = subprocess.Popen([sys.executable, "-m", "reradar_core.cli", "serve", "--port", str(port),
                                 "--log-level", "warning"], cwd=REPO, env=env, stderr=subprocess.DEVNULL)
        url = f"http://127.0.0.1:{port}"
        try:
            deadline = time.monotonic() + 300
            while True:
                try:
                    if httpx.get(url + "/readyz", timeout=2).status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise SystemExit("service did not start")
                time.sleep(0.5)
            with httpx.Client(base_url=url, timeout=60) as c:
                for i in range(args.warmup):
                    c.post("/localize", data={"map_id": "demo"}, files={"scan": ("q.png", scans[i % len(scans)])})
            print(f"one replica ({os.cpu_count()} CPUs), demo map, inline PNG; load average before: "
                  f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}")
            print("clients  requests  localizations/s   p50 ms   p99 ms  errors  localized")
            for c in args.clients:
                r = run(url, scans, c, args.seconds)
                print(f"{c:7d}  {r['requests']:8d}  {r['per_s']:15.2f}  {r['p50_ms']:7.0f}  {r['p99_ms']:7.0f}  "
                      f"{r['errors']:6d}  {r['localized']:9d}   (load avg {os.getloadavg()[0]:.2f})")
        finally:
            proc.terminate()
            proc.wait(timeout=30)


if __name__ == "__main__":
    main()
