"""Sustained throughput of one service replica: C concurrent clients POST /localize for T seconds.

Starts one ``reradar serve`` per ``--workers`` setting (real model, a map, separate processes on free loopback
ports; a private ``redis-server`` when a setting has more than one worker, as ``--workers`` requires), then
for ``--rounds`` rounds runs the C client threads against each server in turn (A B A B ...), so settings are
compared side by side on a shared machine: each client sends the query scans (inline PNG, multipart) back to
back. Prints localizations/s and latency per segment, the median per setting and the ratio to the first
setting round by round, with the load average and the server's memory (RSS and PSS summed over its
processes, from /proc) before and after each segment.

    python benchmarks/bench_throughput.py --workers 1 2 --clients 4 --seconds 30 --rounds 3
    python benchmarks/bench_throughput.py --workers 2 --clients 4 --seconds 600 --rounds 1   # memory over 10 min
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
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


def _tree(pid: int) -> list[int]:
    """``pid`` and its descendants (from /proc)."""
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d.name))
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo.extend(children.get(p, []))
    return out


def memory_mb(pid: int) -> dict[str, float]:
    """RSS, PSS and USS (MB) summed over ``pid`` and its descendants (``smaps_rollup``). PSS counts a page shared
    by k processes as 1/k in each (so it moves when other users' processes map the same libraries, e.g.
    torch's); USS is the tree's private pages only, which no other process affects."""
    rss = pss = uss = 0.0
    for p in _tree(pid):
        try:
            for line in Path(f"/proc/{p}/smaps_rollup").read_text().splitlines():
                if line.startswith("Rss:"):
                    rss += float(line.split()[1]) / 1024
                elif line.startswith("Pss:"):
                    pss += float(line.split()[1]) / 1024
                elif line.startswith(("Private_Clean:", "Private_Dirty:")):
                    uss += float(line.split()[1]) / 1024
        except OSError:
            continue
    return {"rss_mb": rss, "pss_mb": pss, "uss_mb": uss}


def cpu_s(pid: int) -> float:
    """CPU seconds (user + system) used so far by ``pid`` and its descendants, all threads."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for p in _tree(pid):
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        total += (int(fields[11]) + int(fields[12])) / tick
    return total


def run(url: str, map_id: str, scans: list[bytes], clients: int, seconds: float) -> dict[str, float]:
    lat: list[float] = []
    outcomes: dict[str, int] = {}
    lock = threading.Lock()
    stop_at = time.monotonic() + seconds

    def client(k: int) -> None:
        with httpx.Client(base_url=url, timeout=60) as c:
            i = k * 7919
            while time.monotonic() < stop_at:
                t0 = time.perf_counter()
                r = c.post("/localize", data={"map_id": map_id},
                           files={"scan": ("q.png", scans[i % len(scans)])})
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
            "p99_ms": float(np.percentile(a, 99)),
            "errors": sum(v for k, v in outcomes.items() if k.startswith("http_")),
            "localized": outcomes.get("localized", 0)}


def _wait_ready(url: str, proc: subprocess.Popen[bytes], timeout_s: float = 300) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            if httpx.get(url + "/readyz", timeout=2).status_code == 200:
                return
        except httpx.TransportError:
            pass
        if time.monotonic() > deadline or proc.poll() is not None:
            raise SystemExit(f"service at {url} did not start")
        time.sleep(0.5)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, nargs="+", default=[1], help="settings of `reradar serve --workers`")
    ap.add_argument("--clients", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=30.0, help="length of one segment")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=8, help="requests per server before measuring")
    ap.add_argument("--map", type=Path, default=None, help="map .h5 to serve (default: the shipped demo map)")
    ap.add_argument("--queries", type=Path, default=REPO / "maps" / "demo" / "queries",
                    help="folder of query PNGs (sent in a client-specific rotation)")
    ap.add_argument("--max-queries", type=int, default=100)
    ap.add_argument("--json", type=Path, default=None, help="write every segment's figures here")
    ap.add_argument("--setting-env", nargs="*", default=[], metavar="K:NAME=VALUE",
                    help="extra environment of the K-th setting (0-based), e.g. 1:MALLOC_ARENA_MAX=2")
    args = ap.parse_args()

    files = sorted(args.queries.glob("*.png"))
    if len(files) > args.max_queries:  # spread over the route
        files = [files[int(i)] for i in np.linspace(0, len(files) - 1, args.max_queries)]
    scans = [q.read_bytes() for q in files]
    map_id = "demo" if args.map is None else args.map.stem
    procs: list[subprocess.Popen[bytes]] = []
    redis_proc = None
    segments: list[dict[str, object]] = []
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "RERADAR_LOAD_DEMO_MAP": "true" if args.map is None else "false",
               "RERADAR_LOG_FORMAT": "text", "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS", "1")}
        if max(args.workers) > 1:
            rport = _free_port()
            redis_bin = shutil.which("redis-server")
            if redis_bin is None:
                raise SystemExit("--workers > 1 needs redis-server (apt-get install redis-server)")
            redis_proc = subprocess.Popen([redis_bin, "--port", str(rport), "--bind", "127.0.0.1", "--save", "",
                                           "--appendonly", "no"], stdout=subprocess.DEVNULL)
        servers: list[tuple[int, str, subprocess.Popen[bytes]]] = []
        try:
            for k, w in enumerate(args.workers):
                maps_dir = Path(tmp) / f"maps-{k}"
                maps_dir.mkdir()
                if args.map is not None:
                    os.symlink(args.map.resolve(), maps_dir / args.map.name)
                port = _free_port()
                wenv = {**env, "RERADAR_MAPS_DIR": str(maps_dir)}
                for item in args.setting_env:
                    which, _, assignment = item.partition(":")
                    if int(which) == k:
                        name, _, value = assignment.partition("=")
                        wenv[name] = value
                if w > 1:
                    wenv["RERADAR_REDIS_URL"] = f"redis://127.0.0.1:{rport}/{k}"
                proc = subprocess.Popen([sys.executable, "-m", "reradar_cli", "serve", "--port", str(port),
                                         "--workers", str(w), "--log-level", "warning"], cwd=REPO, env=wenv,
                                        stderr=subprocess.DEVNULL)
                procs.append(proc)
                servers.append((w, f"http://127.0.0.1:{port}", proc))
            for _, url, proc in servers:
                _wait_ready(url, proc)
                with httpx.Client(base_url=url, timeout=60) as c:
                    for i in range(args.warmup * 2):  # every worker gets requests
                        c.post("/localize", data={"map_id": map_id}, files={"scan": ("q.png", scans[i % len(scans)])})
            print(f"one replica ({os.cpu_count()} CPUs), map {map_id}, {len(scans)} queries, inline PNG, "
                  f"{args.clients} clients, {args.seconds:.0f} s segments; load average before: "
                  f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
            print("round  workers  requests  localizations/s  p50 ms  p99 ms  errors  localized  server CPU ms/req  "
                  "client CPU ms/req  "
                  "RSS MB (before->after)  PSS MB (before->after)  USS MB (before->after)  load", flush=True)
            for rnd in range(args.rounds):
                for w, url, proc in servers:
                    m0, c0, t0 = memory_mb(proc.pid), cpu_s(proc.pid), os.times()
                    r = run(url, map_id, scans, args.clients, args.seconds)
                    m1, c1, t1 = memory_mb(proc.pid), cpu_s(proc.pid), os.times()
                    r["server_cpu_ms"] = (c1 - c0) * 1e3 / max(1, int(r["requests"]))
                    # this process' own clients (multipart encoding, HTTP) share the machine's cores
                    r["client_cpu_ms"] = ((t1.user - t0.user) + (t1.system - t0.system)) * 1e3 / max(1, int(r["requests"]))
                    seg = {"round": rnd, "workers": w, **r, "rss_before_mb": m0["rss_mb"], "rss_after_mb": m1["rss_mb"],
                           "pss_before_mb": m0["pss_mb"], "pss_after_mb": m1["pss_mb"], "uss_before_mb": m0["uss_mb"],
                           "uss_after_mb": m1["uss_mb"], "load1": os.getloadavg()[0],
                           "utc": time.strftime("%H:%M:%S", time.gmtime())}
                    segments.append(seg)
                    print(f"{rnd:5d}  {w:7d}  {r['requests']:8d}  {r['per_s']:15.2f}  {r['p50_ms']:6.0f}  "
                          f"{r['p99_ms']:6.0f}  {r['errors']:6d}  {r['localized']:9d}  {r['server_cpu_ms']:17.1f}  "
                          f"{r['client_cpu_ms']:17.1f}  "
                          f"{m0['rss_mb']:8.0f} -> {m1['rss_mb']:6.0f}  {m0['pss_mb']:8.0f} -> {m1['pss_mb']:6.0f}  {m0['uss_mb']:8.0f} -> {m1['uss_mb']:6.0f}  "
                          f"{seg['load1']:.2f} ({seg['utc']} UTC)", flush=True)
            base = args.workers[0]
            print("median per setting (ratio to the first setting, round by round):")
            for w in args.workers:
                mine = [s for s in segments if s["workers"] == w]
                rates = [float(s["per_s"]) for s in mine]  # type: ignore[arg-type]
                cpu = [float(s["server_cpu_ms"]) for s in mine]  # type: ignore[arg-type]
                ratios = [float(s["per_s"]) / float(b["per_s"])  # type: ignore[arg-type]
                          for s in mine for b in segments if b["workers"] == base and b["round"] == s["round"]]
                print(f"  workers {w}: {np.median(rates):.2f} localizations/s "
                      f"(min {min(rates):.2f}, max {max(rates):.2f}); ratio to workers {base}: median "
                      f"{np.median(ratios):.2f} (min {min(ratios):.2f}, max {max(ratios):.2f}); server CPU per request "
                      f"{np.median(cpu):.1f} ms")
            if args.json is not None:
                args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                                 "segments": segments}, indent=1))
        finally:
            for proc in procs:
                proc.terminate()
            for proc in procs:
                try:
                    proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    proc.kill()
            if redis_proc is not None:
                redis_proc.terminate()
                redis_proc.wait(timeout=10)


if __name__ == "__main__":
    main()
