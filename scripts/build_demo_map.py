#!/usr/bin/env python3
"""Regenerate the shipped demo map and demo queries (``maps/demo/``) from the simulator's ``smoke`` suite.

    python scripts/build_demo_map.py                 # shipped default weights
    python scripts/build_demo_map.py --weights PATH  # other weights (.pt) or registry name

Writes ``maps/demo/demo.h5`` (the smoke suite's database traversal rendered every 2nd frame, ~3.5 m apart, every
scan a keyframe: the map density ``reradar build-map`` makes from a drive and the confidence is fitted for),
``maps/demo/queries/<t_us>.png`` (evenly spaced scans of the suite's *query* traversal: another drive, 1.5 m
to the side, in snow cover) with ``maps/demo/queries/queries.csv`` (ground-truth map poses) and
``maps/demo/demo.json`` (provenance). Deterministic: the simulator is seeded and the network is run in eval
mode; rerun it whenever the default weights change (the map stores the weights hash and the service refuses
maps built with other weights).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from maps.build import build_map_from_sequence  # noqa: E402
from maps.paths import DEMO_DIR, DEMO_MAP_PATH, DEMO_QUERIES_DIR  # noqa: E402
from maps.store import read_metadata  # noqa: E402
from service.demo import QUERIES_CSV, QueryTruth, write_queries_csv  # noqa: E402

#: Size budget of everything under maps/demo (issue: <= 20 MB).
MAX_DEMO_BYTES = 20 * 2**20


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", default="default", help="model registry name or .pt path")
    parser.add_argument("--suite", default="smoke", help="simulator suite (database -> map, query -> queries)")
    parser.add_argument("--num-queries", type=int, default=8, help="demo query scans to ship")
    parser.add_argument("--every", type=int, default=2,
                        help="frame step of both traversals (the suite's own: 8, keyframes ~14 m apart; 2: ~3.5 m, "
                             "the density the answer confidence is fitted for, docs/MODEL.md 'Sparser maps')")
    parser.add_argument("--limit", type=int, default=80, help="scans per traversal (80 x every 2 = the suite's route)")
    parser.add_argument("--max-keypoints", type=int, default=0,
                        help="cap stored keypoints per keyframe (0: keep the extractor's keypoints, as queries get)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = parser.parse_args()

    import torch

    from reradar_core.io.datasets import load_sequence
    from reradar_core.model import DescriptorExtractor
    from reradar_core.sim.suites import build_suite

    torch.manual_seed(0)
    torch.set_num_threads(args.threads)
    suite = build_suite(args.suite, progress=True, every=args.every, limit=args.limit)
    extractor = DescriptorExtractor.from_pretrained(args.weights)
    print(f"model {extractor.model_id} (weights sha256 {extractor.weights_sha256[:12]}...)")

    DEMO_DIR.mkdir(parents=True, exist_ok=True)
    build_map_from_sequence(suite.database[0], DEMO_MAP_PATH, extractor, layout=suite.layout, preset=suite.preset,
                            batch_size=8, max_keypoints=args.max_keypoints or None, overwrite=True, show_progress=True,
                            name="demo", source=f"reradar sim suite '{args.suite}' / {suite.database[0].name}")

    query = load_sequence(suite.queries[0], suite.layout, suite.preset)
    pick = np.unique(np.linspace(0, len(query) - 1, args.num_queries).round().astype(int))
    shutil.rmtree(DEMO_QUERIES_DIR, ignore_errors=True)
    DEMO_QUERIES_DIR.mkdir(parents=True)
    rows = []
    truth = query.mid_sweep_poses()  # the service answers mid-sweep poses (docs/CONVENTIONS.md)
    for i in pick:
        src = query.scan_paths[i]
        shutil.copyfile(src, DEMO_QUERIES_DIR / src.name)
        x, y, yaw = truth[i]
        rows.append(QueryTruth(src.name, int(query.timestamps_us[i]), float(x), float(y), math.degrees(float(yaw))))
    write_queries_csv(DEMO_QUERIES_DIR / QUERIES_CSV, rows)

    meta = read_metadata(DEMO_MAP_PATH)
    info = {
        "suite": args.suite,
        "database_sequence": suite.database[0].name,
        "query_sequence": suite.queries[0].name,
        "query_condition": suite.query_conditions[0] if suite.query_conditions else None,
        "num_keyframes": meta.num_keyframes,
        "num_queries": len(rows),
        "model_id": meta.model_id,
        "weights_sha256": meta.weights_sha256,
        "max_keypoints": args.max_keypoints,
        "every": args.every,
        "limit": args.limit,
        "command": "python scripts/build_demo_map.py" + ("" if args.weights == "default" else f" --weights {args.weights}"),
    }
    (DEMO_DIR / "demo.json").write_text(json.dumps(info, indent=2) + "\n")
    total = sum(p.stat().st_size for p in DEMO_DIR.rglob("*") if p.is_file())
    print(f"wrote {DEMO_MAP_PATH} ({DEMO_MAP_PATH.stat().st_size / 1e6:.2f} MB, {meta.num_keyframes} keyframes) and "
          f"{len(rows)} queries; maps/demo total {total / 1e6:.2f} MB")
    if total > MAX_DEMO_BYTES:
        print(f"error: maps/demo is {total / 2**20:.1f} MiB > 20 MiB; lower --max-keypoints or --num-queries",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
