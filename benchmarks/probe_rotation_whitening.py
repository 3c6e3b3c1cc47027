"""Probe: how far the learned whitening undoes a model's rotation invariance, and what keeping turned copies together
costs retrieval (issue 11, "global cosine >= 0.95 for arbitrary rotations"; docs/MODEL.md, "Rotation consistency").

For each model: raw NetVLAD vectors (the plain network, eval mode) of the split's training scans (centre views) and of
each turned by a random heading (the same headings ``reradar train --learned-whitening`` draws), then the projection
re-fitted offline with the turned-copy pairs weighted 1 / 10 / 100 against the other-traversal pairs. Each projection
(and the model's own, and raw NetVLAD) is scored on
- the eleven real Oxford scans turned by 15...345 degrees (azimuths shifted, rendered from the polar scan): cosine of
  each turned copy to its unturned scan, min / mean;
- the split's unseen ``confidence`` sessions (every 2nd scan) against its domain's map drive: descriptor-alone
  Recall@1 of the revisits, as recorded and turned by a random heading (training data only, never a benchmark query).

Usage:
    python benchmarks/probe_rotation_whitening.py --split train-target-offroad --models our-3-offroad-w05 M.pt
"""
import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from reradar_core.geometry.cartesian import polar_to_cartesian  # noqa: E402
from reradar_core.geometry.heading import turn_scan  # noqa: E402
from reradar_core.io.scan import load_scan  # noqa: E402
from reradar_core.model import DescriptorExtractor  # noqa: E402
from reradar_core.sim.suites import build_suite  # noqa: E402
from reradar_core.training.cli import _cached  # noqa: E402
from reradar_core.training.data import TrainingSet  # noqa: E402
from reradar_core.training.suites import TRAINING_SPLITS, suite_training_data  # noqa: E402
from reradar_core.training.trainer import recall_at_1_from_descriptors  # noqa: E402
from reradar_core.training.whitening import learned_whitening, matching_pairs  # noqa: E402


def _norm(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def probe(model: str, split: str, oxford: Path, weights: list[int], shrinkage: float) -> list[dict]:
    ex = DescriptorExtractor.from_pretrained(model)
    cc = ex.cartesian
    w = ex.config.cartesian_width_px

    @torch.no_grad()
    def raw(imgs) -> np.ndarray:
        out = []
        for k in range(0, len(imgs), 16):
            _, f = ex.net(torch.as_tensor(np.asarray(imgs[k:k + 16], np.float32))[:, None])
            out.append(ex.net.vlad(f).double().numpy())
        return np.concatenate(out)

    plan = suite_training_data(split, progress=False)
    data = TrainingSet([_cached(s, w, ex.config.cartesian_resolution_m, False) for s in plan.train])
    items = np.arange(len(data))
    r_train = raw(np.stack([data.view(int(i), w, np.zeros(3)) for i in items]))
    yaw = np.random.default_rng([0, 20_000_003]).uniform(0.0, 2 * math.pi, len(items))  # as the trainer's seed 0
    r_turn = raw(np.stack([data.view(int(i), w, np.array([0.0, 0.0, yaw[k]])) for k, i in enumerate(items)]))
    pairs = matching_pairs(data.xy, data.seq_index, data.group, 10.0)
    scans = [load_scan(p, "oxford") for p in sorted(oxford.glob("*.png"))]
    thetas = np.arange(15, 360, 15)
    ox0 = raw(np.stack([polar_to_cartesian(s, cc) for s in scans]))
    oxt = [raw(np.stack([polar_to_cartesian(turn_scan(s, math.radians(t)), cc) for s in scans])) for t in thetas]
    sd, bench = build_suite(split, progress=False), build_suite(TRAINING_SPLITS[split], progress=False)
    db = bench.load(bench.database[0])
    db_xy = np.asarray(db.poses.poses)[:, :2]
    r_db = raw(np.stack([polar_to_cartesian(db.load_scan(i), cc) for i in range(len(db))]))
    rng = np.random.default_rng(0)
    sessions = []
    for qp in sd.confidence:
        q = sd.load(qp)
        idx = np.arange(0, len(q), 2)
        sc = [q.load_scan(int(i)) for i in idx]
        turns = rng.uniform(0, 2 * np.pi, len(sc))
        sessions.append((qp.name, np.asarray(q.poses.poses)[idx, :2], raw(np.stack([polar_to_cartesian(s, cc) for s in sc])),
                         raw(np.stack([polar_to_cartesian(turn_scan(s, a), cc) for s, a in zip(sc, turns, strict=True)]))))
    rows = []

    def score(tag: str, P: np.ndarray | None, b: np.ndarray | None) -> None:
        f = _norm if P is None else (lambda r: _norm(r @ P.T + b))
        g0 = f(ox0)
        cs = np.stack([np.sum(g0 * f(o), 1) for o in oxt])
        row = {"model": Path(model).name, "split": split, "projection": tag,
               "oxford_turned_cosine_min": round(float(cs.min()), 4),
               "oxford_turned_cosine_mean": round(float(cs.mean()), 4)}
        gd = f(r_db)
        for name, qxy, rq0, rqt in sessions:
            r1, n = recall_at_1_from_descriptors(gd, db_xy, f(rq0), qxy, bench.radius_m)
            r1t, _ = recall_at_1_from_descriptors(gd, db_xy, f(rqt), qxy, bench.radius_m)
            row[name] = {"revisits": n, "recall_at_1": round(100 * r1, 2), "recall_at_1_turned": round(100 * r1t, 2)}
        rows.append(row)
        print(json.dumps(row), flush=True)

    score("raw NetVLAD", None, None)
    score("the model's own", ex.net.proj.weight.detach().double().numpy(), ex.net.proj.bias.detach().double().numpy())
    for k in weights:
        a = np.concatenate([r_train[pairs[:, 0]]] + [r_train] * k)
        b = np.concatenate([r_train[pairs[:, 1]]] + [r_turn] * k)
        P, bias = learned_whitening(a, b, r_train, ex.net.proj.out_features, shrinkage)
        score(f"learned whitening, turned pairs x{k}", P, bias)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", nargs="+", required=True, help="shipped names or .pt paths")
    ap.add_argument("--split", default="train-target-offroad")
    ap.add_argument("--oxford", type=Path, default=Path(__file__).resolve().parents[2] / "shared/data/real-oxford/radar")
    ap.add_argument("--weights", type=int, nargs="+", default=[1, 10, 100])
    ap.add_argument("--shrinkage", type=float, default=0.1)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    rows = [r for m in args.models for r in probe(m, args.split, args.oxford, args.weights, args.shrinkage)]
    if args.json:
        args.json.write_text("\n".join(json.dumps(r) for r in rows) + "\n")


if __name__ == "__main__":
    main()
