"""Map memory of 1 vs 2 serving processes, with and without shared (memory-mapped) map arrays.

What a serving worker holds of a map is measured directly, without the model: each process opens the map as
the service does (``maps.database.MapDatabase``: FAISS index, keyframe cache, every keyframe preloaded) -
either reading the keyframes into its own memory (``private``, the behaviour before ``maps.arrays``) or from
the map's shared arrays file (``shared``) - then localizes a few queries (keyframe features, shifted) and,
with ``--touch-all``, reads every page of the arrays file, so the whole map is resident whatever the queries
touched. The processes start together; the benchmark reads ``/proc/PID/smaps_rollup`` of every process at the
same moments - after imports (baseline) and after loading + querying - so a page shared by both is counted
as shared in both readings. Printed per setting: RSS, PSS and USS (private pages) that the map added, per
process and summed, with the load average.

    python benchmarks/bench_map_memory.py --map maps/demo/demo.h5
    python benchmarks/bench_map_memory.py --map .cache/reradar/bench/service/boreas-sim-v4-clear-2238.h5
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def rollup(pid: int) -> dict[str, float]:
    """Memory of one process, MB: ``rss``, ``pss``, ``uss`` (private clean + dirty) and ``anon`` (anonymous:
    heap, not file pages) from ``/proc/PID/smaps_rollup``; ``arrays_rss`` / ``arrays_pss`` / ``arrays_uss``:
    the same of its mappings of shared map arrays files (``*.rrarr``, from ``/proc/PID/smaps``)."""
    out = dict.fromkeys(("rss", "pss", "uss", "anon", "arrays_rss", "arrays_pss", "arrays_uss"), 0.0)
    for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
        key, _, rest = line.partition(":")
        value = float(rest.split()[0]) / 1024 if rest.strip() and rest.split()[0].isdigit() else 0.0
        if key in ("Rss", "Pss"):
            out[key.lower()] += value
        elif key in ("Private_Clean", "Private_Dirty"):
            out["uss"] += value
        elif key == "Anonymous":
            out["anon"] += value
    in_arrays = False
    for line in Path(f"/proc/{pid}/smaps").read_text().splitlines():
        head = line.split()
        if head and "-" in head[0] and len(head) >= 5 and not head[0].endswith(":"):  # a mapping's first line
            in_arrays = line.endswith(".rrarr")
        elif in_arrays and head:
            key = head[0].rstrip(":")
            if key in ("Rss", "Pss"):
                out[f"arrays_{key.lower()}"] += float(head[1]) / 1024
            elif key in ("Private_Clean", "Private_Dirty"):
                out["arrays_uss"] += float(head[1]) / 1024
    return out


def child(map_path: str, arrays_dir: str, queries: int, touch_all: bool) -> None:
    """One serving process: import, wait; load, wait; query, wait; exit. Talks over stdin / stdout lines."""
    # the libraries a query loads (torch, faiss, opencv, scipy) belong to the baseline, not to the map
    import cv2  # noqa: F401
    import faiss  # noqa: F401
    import numpy as np
    import scipy.spatial  # noqa: F401

    from maps.database import MapDatabase
    from maps.store import open_map
    from reradar_core.features import ScanFeatures
    from reradar_core.localization import LocalizationConfig
    from reradar_core.localization.screening import _topk_indices

    _topk_indices(np.zeros((1, 1, 8), np.float32), 2)
    print("base", flush=True)
    sys.stdin.readline()
    db = MapDatabase(open_map(map_path), keyframe_cache_size=None, config=LocalizationConfig(), preload=True,
                     arrays_dir=arrays_dir or None)
    print("loaded", flush=True)
    sys.stdin.readline()
    step = max(1, len(db) // max(1, queries))
    with open_map(map_path) as m:
        for i in range(0, len(db), step)[:queries]:
            f = m.read_keyframe(i)
            db.localize(ScanFeatures(f.global_descriptor, f.keypoints_xy_m + np.float32(0.4), f.local_descriptors))
    if touch_all and db.arrays is not None:
        int(np.frombuffer(db.arrays._mmap, np.uint8)[::4096].sum())  # fault in every page of the file
    print("done", flush=True)
    sys.stdin.readline()


def run_setting(map_path: Path, procs: int, shared: bool, arrays_dir: Path, queries: int,
                touch_all: bool) -> dict[str, object]:
    env = {**os.environ, "PYTHONPATH": str(REPO), "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, __file__, "--child", str(map_path), str(arrays_dir) if shared else "",
           str(queries), "1" if touch_all else "0"]
    ps = [subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env, cwd=REPO)
          for _ in range(procs)]

    def wait_all(word: str) -> None:
        for p in ps:
            assert p.stdout is not None
            line = p.stdout.readline().strip()
            if line != word:
                raise RuntimeError(f"child said {line!r}, expected {word!r} (exit {p.poll()})")

    def tell_all() -> None:
        for p in ps:
            assert p.stdin is not None
            p.stdin.write("go\n")
            p.stdin.flush()

    wait_all("base")
    base = [rollup(p.pid) for p in ps]
    tell_all()
    wait_all("loaded")
    loaded = [rollup(p.pid) for p in ps]
    tell_all()
    wait_all("done")
    after = [rollup(p.pid) for p in ps]
    tell_all()
    for p in ps:
        p.wait(timeout=120)
    per = []
    for b, m, a in zip(base, loaded, after, strict=True):
        d = {k: a[k] - b[k] for k in a}
        d["load_heap"] = m["anon"] - b["anon"]  # what opening the map kept (index, keyframes, screen data)
        d["query_heap"] = a["anon"] - m["anon"]  # what the queries added (grids, allocator pools, torch)
        per.append(d)
    return {"processes": procs, "mode": "shared" if shared else "private", "per_process": per}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--map", type=Path, default=REPO / "maps" / "demo" / "demo.h5")
    ap.add_argument("--queries", type=int, default=20, help="localizations per process after loading")
    ap.add_argument("--no-touch-all", dest="touch_all", action="store_false",
                    help="do not fault in the whole arrays file (only what the queries read)")
    ap.add_argument("--json", type=Path, help="write the results here as well")
    args = ap.parse_args()
    results = []
    with tempfile.TemporaryDirectory(prefix="reradar-arrays-") as tmp:
        arrays_dir = Path(tmp)
        # build the arrays file once up front, so the shared rows measure serving, not the one-off build
        subprocess.run([sys.executable, "-c", "import sys; from maps.database import MapDatabase; "
                        "from maps.store import open_map; MapDatabase(open_map(sys.argv[1]), arrays_dir=sys.argv[2])",
                        str(args.map), str(arrays_dir)], check=True, cwd=REPO,
                       env={**os.environ, "PYTHONPATH": str(REPO)})
        size_mb = sum(p.stat().st_size for p in arrays_dir.glob("*.rrarr")) / 1e6
        for shared in (False, True):
            for procs in (1, 2):
                r = run_setting(args.map, procs, shared, arrays_dir, args.queries, args.touch_all)
                r["load_avg"] = os.getloadavg()[0]
                results.append(r)
    print(f"map {args.map.name}: {args.map.stat().st_size / 1e6:.1f} MB HDF5, arrays file {size_mb:.1f} MB; "
          f"MB the map added per process (after loading + {args.queries} queries"
          f"{', whole arrays file faulted in' if args.touch_all else ''}); load average {os.getloadavg()[0]:.2f}")
    print("  load heap = anonymous memory opening the map kept (index, keyframe copies or views, screen data);")
    print("  query heap = anonymous memory the queries added (pose grids, allocator pools); arrays = the mapped")
    print("  file's pages; map PSS / USS = all heap + arrays PSS / private pages; rollup = smaps_rollup deltas")
    cols = ("load heap", "query heap", "arrays RSS", "arrays PSS", "map PSS", "map USS", "rollup PSS")
    print(f"{'mode':8} {'procs':>5} " + " ".join(f"{c:>13}" for c in cols) + f" {'map USS sum':>11} {'load avg':>8}")
    for r in results:
        per = r["per_process"]
        assert isinstance(per, list)
        rows = [[d["load_heap"], d["query_heap"], d["arrays_rss"], d["arrays_pss"], d["anon"] + d["arrays_pss"],
                 d["anon"] + d["arrays_uss"], d["pss"]] for d in per]
        cells = [" / ".join(f"{row[j]:.1f}" for row in rows) for j in range(len(cols))]
        print(f"{r['mode']:8} {r['processes']:>5} " + " ".join(f"{c:>13}" for c in cells)
              + f" {sum(row[5] for row in rows):>11.1f} {r['load_avg']:>8.2f}")
    if args.json:
        args.json.write_text(json.dumps({"map": str(args.map), "arrays_mb": size_mb, "results": results}, indent=1))


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(sys.argv[2], sys.argv[3], int(sys.argv[4]), sys.argv[5] == "1")
    else:
        main()
