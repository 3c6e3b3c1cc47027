"""Server-side work of one localization, in-process: decode the PNG, extract features, localize - wall and CPU
time per stage - for this checkout and, side by side, another one.

On a shared machine wall-clock latency mostly measures how long a request waited for a core; the CPU time a
request's thread used (``time.thread_time``; torch, BLAS and OpenCV run 1 thread, as in the service) is what a
code change moves. Each round starts one process per checkout (``--baseline DIR``: e.g. ``git worktree add`` or
``git archive`` of the previous commit), alternating A B A B, each sending every query ``--reps`` times
through the service's own calls (``load_scan_bytes``, ``DescriptorExtractor.describe``, ``MapDatabase.localize``
with the map preloaded as the service loads it). Also checks that both checkouts give the same answers
(status, keyframe, pose to the bit).

    python benchmarks/bench_request_cpu.py --baseline /tmp/base --rounds 3
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def child(map_path: str, queries: list[str], reps: int, arrays_dir: str) -> None:
    """Measure one checkout (the one on PYTHONPATH); print one JSON line."""
    import time

    import torch

    torch.set_num_threads(1)
    from maps.database import MapDatabase
    from maps.store import open_map
    from reradar_core.io.scan import load_scan_bytes
    from reradar_core.localization.extractor import load_default_extractor

    extractor = load_default_extractor()
    kwargs: dict[str, object] = {"keyframe_cache_size": 1000, "preload": True}
    if arrays_dir:
        try:
            kwargs["arrays_dir"] = arrays_dir
            db = MapDatabase(open_map(map_path), **kwargs)  # type: ignore[arg-type]
        except TypeError:  # a checkout without shared map arrays
            kwargs.pop("arrays_dir")
            db = MapDatabase(open_map(map_path), **kwargs)  # type: ignore[arg-type]
    else:
        db = MapDatabase(open_map(map_path), **kwargs)  # type: ignore[arg-type]
    data = [(q, Path(q).read_bytes()) for q in queries]
    rows, answers = [], []
    for rep in range(reps + 1):
        for name, blob in data:
            w0, c0 = time.perf_counter(), time.thread_time()
            scan = load_scan_bytes(blob, name)
            w1, c1 = time.perf_counter(), time.thread_time()
            features = extractor.describe(scan)
            w2, c2 = time.perf_counter(), time.thread_time()
            result = db.localize(features)
            w3, c3 = time.perf_counter(), time.thread_time()
            if rep == 0:  # warm-up; its answers are compared
                answers.append([result.status, None if result.best is None else result.best.keyframe_id,
                                None if result.T_map_query is None else result.T_map_query.tolist()])
                continue
            rows.append({"decode_wall": w1 - w0, "extract_wall": w2 - w1, "localize_wall": w3 - w2,
                         "total_wall": w3 - w0, "decode_cpu": c1 - c0, "extract_cpu": c2 - c1,
                         "localize_cpu": c3 - c2, "total_cpu": c3 - c0})
    print(json.dumps({"rows": rows, "answers": answers}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", type=Path, help="another checkout to run side by side (A = this one, B = it)")
    ap.add_argument("--map", type=Path, default=REPO / "maps" / "demo" / "demo.h5")
    ap.add_argument("--queries", type=Path, default=REPO / "maps" / "demo" / "queries")
    ap.add_argument("--limit", type=int, default=20, help="query PNGs used (evenly spread)")
    ap.add_argument("--reps", type=int, default=3, help="passes over the queries per process")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    files = sorted(str(p) for p in args.queries.glob("*.png"))
    files = files[:: max(1, len(files) // args.limit)][: args.limit]
    checkouts = [("this", REPO)] + ([("baseline", args.baseline.resolve())] if args.baseline else [])
    results: dict[str, list[dict[str, float]]] = {name: [] for name, _ in checkouts}
    answers: dict[str, list[object]] = {}
    loads = []
    with tempfile.TemporaryDirectory(prefix="reradar-arrays-") as arrays_dir:
        for _ in range(args.rounds):
            for name, root in checkouts:
                loads.append(os.getloadavg()[0])
                env = {**os.environ, "PYTHONPATH": str(root), "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
                out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", str(args.map),
                                      str(args.reps), arrays_dir, *files], cwd=root, env=env, check=True,
                                     capture_output=True, text=True).stdout
                got = json.loads(out.strip().splitlines()[-1])
                results[name] += got["rows"]
                answers[name] = got["answers"]
    print(f"{len(files)} queries x {args.reps} reps x {args.rounds} rounds per checkout, map {args.map.name}; "
          f"load average {min(loads):.2f}-{max(loads):.2f}")
    keys = ["decode", "extract", "localize", "total"]
    print(f"{'checkout':9} " + " ".join(f"{k + ' wall/cpu p50':>22}" for k in keys))
    med = {name: {f"{k}_{m}": float(np.median([r[f'{k}_{m}'] for r in rows])) * 1e3 for k in keys
                  for m in ("wall", "cpu")} for name, rows in results.items()}
    for name in results:
        print(f"{name:9} " + " ".join(f"{med[name][k + '_wall']:>10.1f} / {med[name][k + '_cpu']:>6.1f} ms"
                                      for k in keys))
    if args.baseline:
        print(f"{'ratio':9} " + " ".join(
            f"{med['this'][k + '_wall'] / med['baseline'][k + '_wall']:>10.2f} / "
            f"{med['this'][k + '_cpu'] / med['baseline'][k + '_cpu']:>6.2f}   " for k in keys))
        same = answers["this"] == answers["baseline"]
        print(f"answers (status, keyframe, pose) identical: {same}")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(sys.argv[2], sys.argv[5:], int(sys.argv[3]), sys.argv[4])
    else:
        main()
