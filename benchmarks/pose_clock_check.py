"""The pose-clock check (``reradar_core.localization.pose_clock``, run by every map build) on rendered drives: how
often it refuses poses on the scans' own clock (false refusals), and whether it finds pose files read at other
times (a pose file on another clock), by how much it is off when it does.

Each sequence is described once with the default model and its consecutive scans registered once (as
``maps.build.build_map`` does); the check then runs on the poses read at mid-sweep time + each shift (what a pose
file that many seconds off the scans' clock gives the map).

Usage:
    python benchmarks/pose_clock_check.py --sequences DIR [DIR ...] [--shifts 0,0.25,0.5,1,2,18,-1,-18] [--json F]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from reradar_core.io.datasets import load_sequence, pose_file_reader  # noqa: E402
from reradar_core.io.presets import mid_sweep_times_us  # noqa: E402
from reradar_core.localization import LocalizationConfig  # noqa: E402
from reradar_core.localization.extractor import load_default_extractor  # noqa: E402
from reradar_core.localization.pose_clock import (  # noqa: E402
    PoseClockConfig,
    consecutive_registrations,
    pose_clock_offset,
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sequences", nargs="+", type=Path, required=True, help="Rendered sequence folders.")
    ap.add_argument("--shifts", default="0,0.25,0.5,1,2,18,-0.5,-1,-18",
                    help="Seconds the poses are read after the scans' times (0: the scans' own clock).")
    ap.add_argument("--model", default=None, help="Model name or .pt (default: the service's default model).")
    ap.add_argument("--json", type=Path, default=None, help="Append one JSON row per sequence and shift.")
    ap.add_argument("--keyframes-only", action="store_true",
                    help="Read shifted poses between keyframes (as a service build does) instead of in the pose file.")
    args = ap.parse_args()
    shifts = [float(s) for s in args.shifts.split(",")]
    extractor = load_default_extractor(args.model or "default")
    config = LocalizationConfig()
    align = replace(config.alignment, min_inliers=config.min_inliers)
    check = PoseClockConfig()
    print(f"{'sequence':48s} {'kf':>5s} {'turns':>5s} " + " ".join(f"{s:>+7.2f}s" for s in shifts))
    for folder in args.sequences:
        seq = load_sequence(folder)
        t0 = time.perf_counter()
        feats = []
        for start in range(0, len(seq), 8):
            feats += extractor.describe_batch([seq.load_scan(i) for i in range(start, min(len(seq), start + 8))])
        t1 = time.perf_counter()
        T_prev_next, ratio = consecutive_registrations(feats.__getitem__, len(feats), align)
        t2 = time.perf_counter()
        track = seq.track if seq.track is not None and len(seq.track) else seq.poses
        mid = mid_sweep_times_us(seq.timestamps_us, seq.preset)
        reader = pose_file_reader(track, seq.preset)  # as maps.build_map_from_sequence reads it: NaN beyond the file
        cells = []
        pairs = 0
        for s in shifts:
            shift_us = int(round(s * 1e6))
            poses = track.interpolate(mid + shift_us)

            def pose_at(t_us: np.ndarray, shift_us: int = shift_us,
                        read: Callable[[np.ndarray], np.ndarray] = reader) -> np.ndarray:
                return read(np.asarray(t_us, np.int64) + shift_us)  # a pose file shift_us behind the scans' clock

            out = pose_clock_offset(T_prev_next, ratio, seq.timestamps_us, poses, check,
                                    None if args.keyframes_only else pose_at)
            pairs = max(pairs, out.pairs)
            cells.append(f"{out.offset_s:+.2f}{'!' if out.offset_detected else ' '}" if out.pairs else "   n/a ")
            if args.json is not None:
                with args.json.open("a") as fh:
                    fh.write(json.dumps({"sequence": str(folder), "shift_s": s, "keyframes": len(seq),
                                     "keyframes_only": args.keyframes_only,
                                         "describe_s": round(t1 - t0, 2), "register_s": round(t2 - t1, 2),
                                         **asdict(out)}) + "\n")
        name = "/".join(Path(folder).parts[-2:])
        print(f"{name:48s} {len(seq):5d} {pairs:5d} "
              + " ".join(f"{c:>8s}" for c in cells) + f"   (register {t2 - t1:.1f} s)", flush=True)


if __name__ == "__main__":
    main()
