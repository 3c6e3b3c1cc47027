"""What ReFeree and RingKey consume, on real vs simulated scans (docs/SIMULATOR.md, "ReFeree and RingKey: what
the simulator gets wrong (diagnosis)").

Usage:
    python scripts/referee_stats.py --real ../shared/data/real-oxford [--sim FOLDER ...] [--consecutive 11]

Prints one Markdown table row per data set: scans; the ReFeree detector's (the authors' Cen 2018 variant,
``reradar_core.baselines.referee``) features per scan and per range band; the strength of the detected peaks
(max q / sigma_q within +-3 bins); mean power per range band; the fraction of zero bins; and, for
consecutive scans (the real folder, and ``--consecutive`` N scans rendered along the ``calib-oxford`` drive in
memory, one traversal, every frame), how far the ReFeree-R descriptor (free-space counts per 80-bin ring) and
the RingKey descriptor (mean power per ring) move between scans 1, 3 and 10 frames apart.

``--sim`` takes any sequence folder (e.g. ``<cache>/sim/v<SIM_VERSION>/calib-oxford/clear``); its scans are not consecutive
(every 24th frame), so it gets no descriptor-change columns. Ranges are in metres, so presets with other bin
sizes compare. The real folder is read, never copied.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from reradar_core.baselines.referee import feature_image, r_referee, referee_features  # noqa: E402
from reradar_core.baselines.ringkey import ring_key  # noqa: E402
from reradar_core.io.datasets import load_sequence  # noqa: E402
from reradar_core.io.scan import RadarScan  # noqa: E402

FEATURE_BANDS_M = (0.0, 5.0, 10.0, 25.0, 50.0, 100.0, 165.0)
POWER_BANDS_M = (0.0, 2.0, 5.0, 10.0, 25.0, 50.0, 100.0, 165.0)
GAPS = (1, 3, 10)


def peak_strength(power: np.ndarray) -> np.ndarray:
    """q / sigma_q at each ReFeree feature (max of q within +-3 bins), the detector's own noise estimate."""
    x = np.asarray(power, dtype=np.float64)
    q = x - x.mean(axis=1, keepdims=True)
    neg = q < 0
    sigma = np.sqrt(np.where(neg, q * q, 0.0).sum(axis=1) / np.maximum(neg.sum(axis=1), 1))
    rows, bins = referee_features(x)
    qmax = ndimage.maximum_filter1d(q, 7, axis=1)
    return qmax[rows, bins] / np.maximum(sigma[rows], 1e-12)


def scan_statistics(scans: list[RadarScan], consecutive: bool) -> dict[str, object]:
    """Statistics of one set of scans (see the module docstring)."""
    feat_h, pow_b, strength, zero = [], [], [], []
    for s in scans:
        rows, bins = referee_features(s.power)
        rng = bins * s.range_resolution_m + s.range_offset_m
        feat_h.append(np.histogram(rng, FEATURE_BANDS_M)[0])
        r = s.range_offset_m + np.arange(s.power.shape[1]) * s.range_resolution_m
        pow_b.append([float(s.power[:, (r >= a) & (r < b)].mean()) for a, b in zip(POWER_BANDS_M[:-1],
                                                                                       POWER_BANDS_M[1:],
                                                                                       strict=True)])
        strength.append(peak_strength(s.power))
        zero.append(float(np.mean(s.power == 0)))
    h = np.asarray(feat_h, dtype=np.float64)
    st = np.concatenate(strength)
    out: dict[str, object] = {"scans": len(scans), "features": h.sum(axis=1).mean(), "feature_bands": h.mean(axis=0),
                              "power_bands": np.mean(pow_b, axis=0), "strength_p50": float(np.median(st)),
                              "strength_p90": float(np.quantile(st, 0.9)), "zero": float(np.mean(zero))}
    if consecutive:
        rr = np.stack([r_referee(feature_image(s.power)) for s in scans])
        kk = np.stack([ring_key(s.power) for s in scans])
        for g in GAPS:
            if g < len(scans):
                out[f"dR{g}"] = float(np.mean(np.linalg.norm(rr[g:] - rr[:-g], axis=1)))
                out[f"dK{g}"] = float(np.mean(np.linalg.norm(kk[g:] - kk[:-g], axis=1)))
    return out


def render_consecutive(n: int, offset: int = 0) -> tuple[list[RadarScan], float]:
    """``n`` consecutive scans (every frame) of the ``calib-oxford`` clear traversal from frame ``offset``;
    returns the scans and the median step between them (m)."""
    from reradar_core.sim import suites as S
    from reradar_core.sim.sensor import render_scan, scan_seed
    from reradar_core.sim.traversal import Traversal
    from reradar_core.sim.world import RoadNetwork, World

    suite = S.SUITES["calib-oxford"]
    seq = replace(next(s for s in suite.sequences if s.name == "clear"), every=1, limit=n, offset=offset)
    road = RoadNetwork([S._route_trajectory(replace(r, lateral_m=0.0), None).xy for r in suite.road_routes])
    world = World(road, seed=suite.world_seed, profile=suite.profile)
    traj = S._route_trajectory(seq.route, None)
    t, idx = S._sequence_times(traj, seq, use_pose_times=False)
    trav = Traversal(world, seq.traversal_seed, seq.condition, traffic_per_km=suite.traffic_per_km)
    scans = [render_scan(trav, traj, int(t0), suite.preset, scan_seed(trav.seed, int(k))) for t0, k in
             zip(t, idx, strict=True)]
    xy = traj.interpolate(t)[:, :2]
    return scans, float(np.median(np.hypot(*np.diff(xy, axis=0).T)))


def table(rows: list[tuple[str, dict[str, object]]]) -> str:
    fb = "/".join(f"{a:.0f}-{b:.0f}" for a, b in zip(FEATURE_BANDS_M[:-1], FEATURE_BANDS_M[1:], strict=True))
    pb = "/".join(f"{a:.0f}-{b:.0f}" for a, b in zip(POWER_BANDS_M[:-1], POWER_BANDS_M[1:], strict=True))
    gaps = "/".join(str(g) for g in GAPS)
    out = [f"| data | scans | features / scan | features per band {fb} m | peak q/σ p50 / p90 | mean power {pb} m "
           f"| zero bins | ReFeree-R change, gap {gaps} | RingKey change, gap {gaps} |",
           "|---|---|---|---|---|---|---|---|---|"]
    def gap(st: dict[str, object], k: str) -> str:
        vals = [st.get(f"{k}{g}") for g in GAPS]
        if all(v is None for v in vals):
            return "–"
        fmt = "{:.0f}" if k == "dR" else "{:.3f}"
        return " / ".join("–" if v is None else fmt.format(v) for v in vals)

    for label, st in rows:
        out.append(f"| {label} | {st['scans']} | {st['features']:.0f} | "
                   + " / ".join(f"{x:.0f}" for x in st["feature_bands"])  # type: ignore[attr-defined]
                   + f" | {st['strength_p50']:.1f} / {st['strength_p90']:.1f} | "
                   + " / ".join(f"{x:.3f}" for x in st["power_bands"])  # type: ignore[attr-defined]
                   + f" | {st['zero']:.3f} | {gap(st, 'dR')} | {gap(st, 'dK')} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--real", type=Path, required=True, help="real Oxford folder (radar/ + radar_odometry.csv)")
    ap.add_argument("--sim", type=Path, nargs="*", default=[], help="simulated sequence folders")
    ap.add_argument("--consecutive", type=int, default=11,
                    help="consecutive calib-oxford scans to render per drive offset (0: none)")
    ap.add_argument("--offsets", default="0,150,300,450", help="frame offsets of the consecutive renders")
    a = ap.parse_args(argv)
    real = load_sequence(a.real, preset="oxford")
    rows = [(f"real Oxford ({a.real.name})", scan_statistics([real.load_scan(i) for i in range(len(real))], True))]
    for folder in a.sim:
        seq = load_sequence(folder)
        rows.append((f"sim {folder.parent.name}/{folder.name}",
                     scan_statistics([seq.load_scan(i) for i in range(len(seq))], False)))
    if a.consecutive > 0:
        for off in (int(x) for x in a.offsets.split(",") if x.strip()):
            scans, step = render_consecutive(a.consecutive, off)
            rows.append((f"sim calib-oxford clear, {a.consecutive} consecutive from frame {off} ({step:.1f} m/frame)",
                         scan_statistics(scans, True)))
    print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
