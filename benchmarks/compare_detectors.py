#!/usr/bin/env python3
"""The compiled Cen 2018 detector against the vectorised (OpenCV) one on recorded scans: how many keypoints
differ, how far the strengths move, and the time per scan of each (docs/BENCHMARKS.md, "Session 10").

    python benchmarks/compare_detectors.py SEQUENCE_DIR [SEQUENCE_DIR ...] [--scans 40] [--max-range-m 92.41]

Each sequence contributes ``--scans`` scans spread over it; every scan is detected with ``RERADAR_JIT=0`` and
``1``, with the range limit the descriptor models use (92.41 m: the 201-px, 0.64 m/px image's corners) and
without. Times are for the range-limited detection, Python call included.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from reradar_core.io.datasets import load_sequence  # noqa: E402
from reradar_core.jit import jit_enabled  # noqa: E402
from reradar_core.landmarks import detect_landmarks  # noqa: E402
from reradar_core.landmarks.cen2018_kernels import warm_up  # noqa: E402


def _keys(lm) -> set[tuple[int, int]]:
    return set(zip(lm.azimuth_index.tolist(), lm.range_bin.tolist(), strict=True))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequences", nargs="+", type=Path, help="sequence folders (any supported layout)")
    ap.add_argument("--scans", type=int, default=40, help="scans per sequence, spread evenly")
    ap.add_argument("--max-range-m", type=float, default=92.41)
    args = ap.parse_args()
    os.environ["RERADAR_JIT"] = "1"
    if not jit_enabled():
        print("numba is not installed: there is no compiled detector to compare", file=sys.stderr)
        return 2
    warm_up()
    print("| sequence | scans | keypoints | differing | max strength change (relative) | vectorised ms | compiled ms |")
    print("|---|---|---|---|---|---|---|")
    totals = [0, 0]
    for path in args.sequences:
        seq = load_sequence(path)
        idx = np.unique(np.linspace(0, len(seq) - 1, min(args.scans, len(seq))).round().astype(int))
        n = differing = 0
        rel = 0.0
        t_vec = t_jit = 0.0
        for i in idx:
            scan = seq.load_scan(int(i))
            for max_range in (args.max_range_m, None):
                os.environ["RERADAR_JIT"] = "0"
                t0 = time.perf_counter()
                a = detect_landmarks(scan, None, max_range)
                t1 = time.perf_counter()
                os.environ["RERADAR_JIT"] = "1"
                b = detect_landmarks(scan, None, max_range)
                t2 = time.perf_counter()
                if max_range is not None:
                    t_vec += t1 - t0
                    t_jit += t2 - t1
                ka, kb = _keys(a), _keys(b)
                n += len(ka)
                differing += len(ka ^ kb)
                if ka == kb and len(a):
                    rel = max(rel, float(np.abs(b.strength / a.strength - 1.0).max()))
        totals[0] += n
        totals[1] += differing
        print(f"| {path} | {len(idx)} | {n} | {differing} | {rel:.1e} | {t_vec / len(idx) * 1e3:.2f} | "
              f"{t_jit / len(idx) * 1e3:.2f} |")
    print(f"\nall: {totals[1]} of {totals[0]} keypoints differ")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
