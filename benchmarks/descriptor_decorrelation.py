"""How fast do the baselines' descriptors change as the vehicle drives on? Real Oxford scans vs the simulator.

A realism check against real data (never a benchmark query sequence): for the eleven real Oxford scans (about 1.9 m
apart) and for simulated scans rendered at exactly their poses (the real odometry integrated, the world built
around the surrounding stretch of it, several world seeds), the mean descriptor distance between scans ``g``
frames apart, g = 1 ... 10 (1.9 ... 19 m), for RingKey, ReFeree-R, RaPlace and RadVLAD with their reference
distances (``reradar_core.baselines``; RadVLAD's vocabulary is fitted on the beams of the scan set itself, as the
reference fits it on its reference run, so the real and the simulated sets each get their own). Place recognition
works when that distance grows slowly with the distance driven compared with the distance between unrelated places; a simulator whose descriptors change faster (or slower) per
metre than real ones makes that baseline harder (or easier) than on real data, whatever the weather.

The simulated scans are quantised to 8 bits like the real PNGs. The same scans' intensity statistics
(``reradar_core.sim.stats``: mean, median, 99th percentile, zero bins, bins above the far-range floor, Cen 2018
keypoints) are printed beside, so that a sensor change is judged on both.

``--set`` overrides the world profile, the weather condition and the sensor (ablations, one at a time) with
``benchmarks/calibrate_sim.py``'s keys: ``profile.urban.FIELD=V``, ``cond.clear.FIELD=V``, ``sensor.FIELD=V`` and
``traversal.FIELD=V`` (the
rows recorded on 2026-12-01 before 15:40 UTC wrote the profile keys without the profile name).

    OPENBLAS_NUM_THREADS=1 python benchmarks/descriptor_decorrelation.py ../shared/data/real-oxford \\
        --worlds 1,2,3 [--set profile.urban.parked_car_slot_prob=0.9] [--json rows.jsonl --label L]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from calibrate_sim import _condition, _traversal, parse_overrides, profile_with, sensor_with  # noqa: E402

from reradar_core.baselines.radvlad import RadVLAD  # noqa: E402
from reradar_core.baselines.raplace import RaPlace  # noqa: E402
from reradar_core.baselines.referee import ReFeree  # noqa: E402
from reradar_core.baselines.ringkey import RingKey  # noqa: E402
from reradar_core.io.datasets import Sequence, load_sequence, read_oxford_odometry  # noqa: E402
from reradar_core.io.poses import PoseSequence  # noqa: E402
from reradar_core.io.presets import get_preset  # noqa: E402
from reradar_core.io.scan import RadarScan  # noqa: E402
from reradar_core.sim.sensor import SensorConfig, render_scan, scan_seed  # noqa: E402
from reradar_core.sim.stats import scan_statistics, summarize  # noqa: E402
from reradar_core.sim.traversal import Traversal  # noqa: E402
from reradar_core.sim.world import PROFILES, RoadNetwork, World  # noqa: E402

GAPS = (1, 2, 3, 5, 8, 10)
STATS = ("mean", "p50", "p99", "frac_zero", "frac_above_floor", "keypoints")


def _methods() -> dict[str, object]:
    return {"ringkey": RingKey(), "referee": ReFeree(), "raplace": RaPlace(), "radvlad": RadVLAD()}


def gap_distances(scans: list[RadarScan]) -> dict[str, np.ndarray]:
    """Per method, (len(scans) - 1,) mean reference distance between scans g = 1, 2, ... frames apart."""
    out = {}
    for name, m in _methods().items():
        prepared = [m.prepare(s) for s in scans]  # type: ignore[attr-defined]
        m.fit(prepared)  # type: ignore[attr-defined]  # RadVLAD's vocabulary from this set's beams; a no-op for the rest
        descs = [m.describe_prepared(p) for p in prepared]  # type: ignore[attr-defined]
        index = m.build_index(descs)  # type: ignore[attr-defined]
        dist = np.stack([m.distance(d, index) for d in descs])  # type: ignore[attr-defined]
        n = len(scans)
        out[name] = np.array([np.mean([dist[i, i + g] for i in range(n - g)]) for g in range(1, n)])
    return out


def real_stretch(folder: Path, margin_frames: int = 80) -> tuple[Sequence, PoseSequence, np.ndarray]:
    """The real Oxford scans, the stretch of their integrated odometry ``margin_frames`` either side (the road of
    the simulated world; poses T_first_scan) and each real scan's frame index within that stretch, (N,) int64."""
    real = load_sequence(folder, layout="oxford")
    odo = read_oxford_odometry(folder / "radar_odometry.csv")
    idx = np.searchsorted(odo.timestamps_us, real.poses.timestamps_us)
    if np.any(odo.timestamps_us[np.minimum(idx, len(odo) - 1)] != real.poses.timestamps_us):
        raise SystemExit("the real scans' timestamps are not in radar_odometry.csv")
    lo, hi = max(0, int(idx[0]) - margin_frames), min(len(odo), int(idx[-1]) + margin_frames + 1)
    return real, PoseSequence(odo.timestamps_us[lo:hi], odo.xy[lo:hi], odo.yaw[lo:hi]), (idx - lo).astype(np.int64)


def render_at(trav: Traversal, traj: PoseSequence, times_us: np.ndarray, frames: np.ndarray,
              sensor: SensorConfig = SensorConfig()) -> list[RadarScan]:
    """Oxford-preset scans of ``trav`` starting at ``times_us`` along ``traj`` (per-scan noise seeded by the frame
    index), quantised to 8 bits like the real PNGs."""
    preset = get_preset("oxford")
    out = []
    for t, k in zip(times_us, frames, strict=True):
        s = render_scan(trav, traj, int(t), preset, scan_seed(trav.seed, int(k)), sensor)
        out.append(replace(s, power=np.round(s.power * 255).astype(np.float32) / 255.0))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", help="real-oxford folder (radar/<t>.png + radar_odometry.csv)")
    ap.add_argument("--worlds", default="1,2,3", help="world seeds of the simulated stretch (comma-separated)")
    ap.add_argument("--profile", default="urban", help="world profile (the real scans are urban Oxford)")
    ap.add_argument("--condition", default="clear", help="weather of the simulated drive")
    ap.add_argument("--margin-frames", type=int, default=80,
                    help="odometry frames either side of the real scans that make the simulated world's road")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="profile.NAME.FIELD=V, cond.NAME.FIELD=V, sensor.FIELD=V or traversal.FIELD=V, as "
                         "benchmarks/calibrate_sim.py "
                         "takes them (repeatable)")
    ap.add_argument("--json", default=None, help="append one JSON row here")
    ap.add_argument("--label", default="", help="row label for --json")
    args = ap.parse_args()

    real, traj, frames = real_stretch(Path(args.folder), args.margin_frames)
    real_scans = [real.load_scan(i) for i in range(len(real))]

    overrides = parse_overrides(args.set)
    unknown = [k for k in overrides if not k.startswith(("profile.", "cond.", "sensor.", "traversal."))]
    if unknown:
        raise SystemExit(f"unknown override(s) {unknown}: use profile.{args.profile}.FIELD, "
                         f"cond.{args.condition}.FIELD, sensor.FIELD or traversal.FIELD")
    profile = profile_with(PROFILES[args.profile], overrides)
    condition = _condition(args.condition, overrides)
    sensor = sensor_with(SensorConfig(), overrides)

    t0 = time.perf_counter()
    results = {"real": gap_distances(real_scans)}
    all_sims: list[RadarScan] = []
    for w in (int(s) for s in args.worlds.split(",")):
        trav = _traversal(World(RoadNetwork([traj.xy]), seed=w, profile=profile), w + 1, condition, overrides)
        sims = render_at(trav, traj, real.poses.timestamps_us, frames, sensor)
        results[f"world {w}"] = gap_distances(sims)
        all_sims += sims
    sim_mean = {m: np.mean([results[k][m] for k in results if k != "real"], axis=0) for m in results["real"]}

    gaps = [g for g in GAPS if g < len(real_scans)]
    print(f"load average {os.getloadavg()[0]:.2f}; {time.perf_counter() - t0:.0f} s; overrides {overrides or 'none'}")
    print("| method | scans | " + " | ".join(f"g = {g}" for g in gaps) + " |")
    print("|---|---|" + "---|" * len(gaps))
    for m in results["real"]:
        for scans_name, per_method in results.items():
            print(f"| {m} | {scans_name} | " + " | ".join(f"{per_method[m][g - 1]:.4g}" for g in gaps) + " |")
        ratio = sim_mean[m] / results["real"][m]
        print(f"| {m} | **simulated / real** | " + " | ".join(f"**{ratio[g - 1]:.2f}**" for g in gaps) + " |")
    stats = {name: {n: float(np.asarray(v[n])) for n in STATS}
             for name, v in (("real", summarize([scan_statistics(s) for s in real_scans])),
                             ("simulated", summarize([scan_statistics(s) for s in all_sims])))}
    print("\n| scans | " + " | ".join(STATS) + " |")
    print("|---|" + "---|" * len(STATS))
    for scans_name, figures in stats.items():
        print(f"| {scans_name} | " + " | ".join(f"{figures[n]:.4g}" for n in STATS) + " |")
    if args.json:
        row = {"label": args.label, "overrides": overrides, "profile": args.profile, "condition": args.condition,
               "worlds": args.worlds, "gaps": gaps, "utc": time.strftime("%H:%M:%S", time.gmtime()),
               "load1": round(os.getloadavg()[0], 2),
               **{f"{m}_real": [float(results['real'][m][g - 1]) for g in gaps] for m in results["real"]},
               **{f"{m}_sim": [float(sim_mean[m][g - 1]) for g in gaps] for m in results["real"]},
               "stats_real": stats["real"], "stats_sim": stats["simulated"]}
        with open(args.json, "a") as fh:
            fh.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
