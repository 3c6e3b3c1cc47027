"""Probe: symmetric test-time rotation pooling of the global descriptor (issue 11, "global cosine >= 0.95 for arbitrary
rotations"; docs/MODEL.md, "Rotation pooling at test time, measured"). A measurement, not a shipped option.

Pooled descriptor of a scan s for a pool set P (degrees):
    g_P(s) = L2norm(W @ L2norm(mean_{d in P} rawNetVLAD(turn_scan(s, d))) + b)
with W, b the model's own learned whitening (ex.net.proj) -- exactly DescriptorNet.aggregate's projection + L2.
rawNetVLAD = ex.net.vlad(F') with F' from the shipped runtime (ex.run_images: ONNX Runtime when present),
disc mask as configured (on), i.e. the shipped pipeline up to the projection.
P = {0} is the control (== the shipped descriptor; checked against ex.global_descriptors).
Both sides are pooled alike: map keyframes and queries.

Measures per model:
 1. real Oxford (11 scans, preset oxford): cosine of g_P(scan) vs g_P(turn_scan(scan, theta)), theta = 5..355 step 5;
 2. descriptor-alone Recall@1 on the split's unseen `confidence` sessions (every 2nd scan) against its domain's map
    drive (database[0]), queries as recorded and turned by a random heading (rng default_rng(0), drawn per session
    in order, as benchmarks/probe_rotation_whitening.py); database and queries pooled the same way.

Usage:
    python benchmarks/probe_rotation_pooling.py --model our-3-offroad-w05 --split train-target-offroad \
        --oxford ../shared/data/real-oxford/radar --json out.json
    python benchmarks/probe_rotation_pooling.py --model our-3-loop-w05 --oxford ../shared/data/real-oxford/radar \
        --step 0.625 --pools "0;0,7.5,15,22.5,30,37.5" --json out.json       # Oxford only, a fine grid, one pool set
"""
import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

torch.set_num_threads(1)

from reradar_core.geometry.cartesian import polar_to_cartesian  # noqa: E402
from reradar_core.geometry.heading import turn_scan  # noqa: E402
from reradar_core.io.scan import load_scan  # noqa: E402
from reradar_core.model import DescriptorExtractor  # noqa: E402
from reradar_core.sim.suites import build_suite  # noqa: E402
from reradar_core.training.suites import TRAINING_SPLITS  # noqa: E402
from reradar_core.training.trainer import recall_at_1_from_descriptors  # noqa: E402

#: pool sets (degrees) by name; "none" (the control) must be first. ``--pools`` replaces them.
POOLS = {"none": (0.0,), "0,22.5": (0.0, 22.5), "0,15,30": (0.0, 15.0, 30.0),
         "0,11.25,22.5,33.75": (0.0, 11.25, 22.5, 33.75)}
OFFSETS = sorted({d for p in POOLS.values() for d in p})


def _norm(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


class Pooler:
    def __init__(self, model: str):
        self.ex = DescriptorExtractor.from_pretrained(model)
        self.cc = self.ex.cartesian
        assert not self.ex.config.canonical_heading
        self.W = self.ex.net.proj.weight.detach().double().numpy()
        self.b = self.ex.net.proj.bias.detach().double().numpy()

    @torch.inference_mode()
    def raw(self, imgs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, W, W) images -> (raw NetVLAD (B, 512) float64, shipped global descriptor (B, 256))."""
        out, gs = [], []
        for k in range(0, len(imgs), 16):
            g, f = self.ex.run_images(imgs[k:k + 16])
            out.append(self.ex.net.vlad(torch.from_numpy(np.ascontiguousarray(f)), imgs.shape[-1]).double().numpy())
            gs.append(g)
        return np.concatenate(out), np.concatenate(gs)

    def project(self, v: np.ndarray) -> np.ndarray:
        """raw (already pooled) NetVLAD (..., 512) -> whitened descriptor, as DescriptorNet.aggregate."""
        return _norm(_norm(v) @ self.W.T + self.b)

    def turned_vlads(self, scan, base_rad: float) -> dict[float, np.ndarray]:
        """{offset deg: raw NetVLAD of the scan turned by base + offset}."""
        imgs = np.stack([polar_to_cartesian(turn_scan(scan, base_rad + math.radians(d)), self.cc) for d in OFFSETS])
        v, _ = self.raw(imgs)
        return {d: v[i] for i, d in enumerate(OFFSETS)}


def pooled(vl: list[dict], pool: tuple) -> np.ndarray:
    return np.stack([np.mean([v[d] for d in pool], axis=0) for v in vl])


def oxford(p: Pooler, step: float, folder: Path) -> dict:
    scans = [load_scan(q, "oxford") for q in sorted(Path(folder).glob("*.png"))]
    thetas = np.arange(0.0, 360.0, step)
    angles = sorted({round((t + d) % 360.0, 6) for t in thetas for d in OFFSETS})
    cache = {}  # (scan i, angle) -> raw vlad
    for i, s in enumerate(scans):
        for k in range(0, len(angles), 16):
            chunk = angles[k:k + 16]
            v, _ = p.raw(np.stack([polar_to_cartesian(turn_scan(s, math.radians(a)), p.cc) for a in chunk]))
            for a, vv in zip(chunk, v, strict=True):
                cache[(i, a)] = vv
    res = {}
    for name, pool in POOLS.items():
        def g(i, t, pool=pool):
            return np.mean([cache[(i, round((t + d) % 360.0, 6))] for d in pool], axis=0)
        cs = np.array([[float(p.project(g(i, 0.0)) @ p.project(g(i, t))) for t in thetas[1:]] for i in range(len(scans))])
        rw = np.array([[float(_norm(g(i, 0.0)) @ _norm(g(i, t))) for t in thetas[1:]] for i in range(len(scans))])
        worst = thetas[1:][int(np.argmin(cs.min(0)))]
        res[name] = {"cos_min": round(float(cs.min()), 4), "cos_mean": round(float(cs.mean()), 4),
                     "cos_min_at_deg": float(worst), "raw_min": round(float(rw.min()), 4),
                     "raw_mean": round(float(rw.mean()), 4),
                     "per_theta_min": cs.min(0).round(4).tolist(),
                     "per_theta_mean": cs.mean(0).round(4).tolist(), "thetas": thetas[1:].tolist()}
        print(f"oxford {name:20s} cos min {cs.min():.4f} (at {worst:g}) mean {cs.mean():.4f}; raw min {rw.min():.4f} "
              f"mean {rw.mean():.4f}", flush=True)
    # control check: P={0} via this path vs the shipped extractor on the unturned scans
    ship = p.ex.global_descriptors(scans)
    mine = p.project(np.stack([cache[(i, 0.0)] for i in range(len(scans))]))
    c = (ship * mine).sum(1) / np.linalg.norm(ship, axis=1)
    res["control_vs_shipped_cos_min"] = float(c.min())
    print(f"control check (oxford): cosine own path vs ex.global_descriptors min {c.min():.7f}", flush=True)
    return res


def _hits(gd, db_xy, gq, q_xy, radius):
    d = np.hypot(q_xy[:, None, 0] - db_xy[None, :, 0], q_xy[:, None, 1] - db_xy[None, :, 1])
    valid = d.min(axis=1) <= radius
    top = np.argmax(gq @ gd.T, axis=1)
    return (d[np.arange(len(q_xy)), top] <= radius)[valid]


def retrieval(p: Pooler, split: str, stride: int, db_stride: int, q_start: int = 0) -> dict:
    sd, bench = build_suite(split, progress=False), build_suite(TRAINING_SPLITS[split], progress=False)
    db = bench.load(bench.database[0])
    didx = np.arange(0, len(db), db_stride)
    db_xy = np.asarray(db.poses.poses)[didx, :2]
    t0 = time.time()
    db_v, ship_g, own_g = [], [], []
    for n, i in enumerate(didx):
        s = db.load_scan(int(i))
        db_v.append(p.turned_vlads(s, 0.0))
        if n < 64:  # control check on the first 64 map scans
            ship_g.append(p.ex.global_descriptors([s])[0])
            own_g.append(p.project(db_v[-1][0.0]))
    cc = (np.stack(ship_g) * np.stack(own_g)).sum(1)
    print(f"{split}: map {bench.database[0].name} {len(didx)} scans described in {time.time() - t0:.0f} s; control "
          f"check cosine own vs shipped min {cc.min():.7f}", flush=True)
    rng = np.random.default_rng(0)
    out = {"map": bench.database[0].name, "map_scans": int(len(didx)), "radius_m": bench.radius_m,
           "control_vs_shipped_cos_min": float(cc.min()), "sessions": {}}
    for qp in sd.confidence:
        q = sd.load(qp)
        idx = np.arange(q_start, len(q), 2)
        turns = rng.uniform(0, 2 * np.pi, len(idx))  # same draws as probe_rotation_whitening.py
        keep = np.arange(0, len(idx), stride)  # stride 1 = every 2nd scan, as the probe
        qxy = np.asarray(q.poses.poses)[idx[keep], :2]
        rec, trn = [], []
        for k in keep:
            s = q.load_scan(int(idx[k]))
            rec.append(p.turned_vlads(s, 0.0))
            trn.append(p.turned_vlads(s, float(turns[k])))
        row = {}
        for name, pool in POOLS.items():
            gd = p.project(pooled(db_v, pool))
            r1, n = recall_at_1_from_descriptors(gd, db_xy, p.project(pooled(rec, pool)), qxy, bench.radius_m)
            r1t, _ = recall_at_1_from_descriptors(gd, db_xy, p.project(pooled(trn, pool)), qxy, bench.radius_m)
            row[name] = {"revisits": n, "recall_at_1": round(100 * r1, 2), "recall_at_1_turned": round(100 * r1t, 2)}
            h = {t: _hits(gd, db_xy, p.project(pooled(x, pool)), qxy, bench.radius_m) for t, x in (("rec", rec), ("trn", trn))}
            if name == "none":
                h0 = h
            else:  # paired against the control: queries gained / lost
                row[name]["gained_lost_recorded"] = [int((h["rec"] & ~h0["rec"]).sum()), int((~h["rec"] & h0["rec"]).sum())]
                row[name]["gained_lost_turned"] = [int((h["trn"] & ~h0["trn"]).sum()), int((~h["trn"] & h0["trn"]).sum())]
            print(f"{split} {qp.name} {name:20s} revisits {n}: R@1 {100 * r1:.2f} / turned {100 * r1t:.2f} "
                  f"{row[name].get('gained_lost_recorded', '')} {row[name].get('gained_lost_turned', '')}", flush=True)
        out["sessions"][qp.name] = row
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", required=True)
    ap.add_argument("--split", default=None, help="training split of the retrieval check (none: Oxford only)")
    ap.add_argument("--oxford", type=Path, default=None, help="folder of the real Oxford scans (radar/*.png)")
    ap.add_argument("--pools", default=None, help='pool sets, e.g. "0;0,22.5;0,15,30" (degrees; the first is the control)')
    ap.add_argument("--step", type=float, default=5.0)
    ap.add_argument("--stride", type=int, default=1, help="every n-th of the probe's query scans (every 2nd scan)")
    ap.add_argument("--db-stride", type=int, default=1)
    ap.add_argument("--q-start", type=int, default=0, help="0: even query scans (the probe's), 1: odd ones")
    ap.add_argument("--json", required=True)
    a = ap.parse_args()
    global POOLS, OFFSETS
    if a.pools:
        sets = [tuple(float(x) for x in s.split(",")) for s in a.pools.split(";") if s.strip()]
        POOLS = {("none" if s == (0.0,) else ",".join(f"{x:g}" for x in s)): s for s in sets}
        OFFSETS = sorted({d for p in POOLS.values() for d in p})
    if "none" not in POOLS:
        ap.error("the pool sets must include the control, 0")
    t0 = time.time()
    p = Pooler(a.model)
    print(f"{a.model}: runtime {p.ex.runtime}, torch threads {torch.get_num_threads()}", flush=True)
    res = {"model": a.model, "split": a.split, "pools": POOLS, "step": a.step, "stride": a.stride,
           "db_stride": a.db_stride}
    if a.oxford is not None:
        res["oxford"] = oxford(p, a.step, a.oxford)
        print(f"oxford done {time.time() - t0:.0f} s", flush=True)
    res["q_start"] = a.q_start
    if a.split:
        res["retrieval"] = retrieval(p, a.split, a.stride, a.db_stride, a.q_start)
    res["wall_s"] = round(time.time() - t0, 1)
    Path(a.json).write_text(json.dumps(res, indent=1))
    print(f"done {res['wall_s']} s", flush=True)


if __name__ == "__main__":
    main()
