"""Probe: a canonical heading for the global descriptor (issue 11, "global cosine >= 0.95 for arbitrary rotations").

The C8 network is exactly invariant to 90-degree turns of its input, and only approximately between them (the
whitened descriptor's cosine falls to ~0.82 at 1 degree, docs/MODEL.md). A turn of the sensor is an exact shift of
the scan's azimuth labels, so an orientation read from the polar scan by a rotation-*equivariant* rule, taken modulo
90 degrees, can turn every scan to a canonical heading before the network: a turned copy then gives the same image
and the same descriptor at any angle. Whether that helps or hurts retrieval depends on how stable the canonical
heading is between two passes of a place (weather, a few metres of offset); that is what this probe measures, on a
training split's validation tails only (map tail vs each traversal's tail; never a benchmark query sequence).

Canonical-heading rules (angle psi mod 90 deg; the image is rendered with azimuths + shift, shift = -psi):
- ``profile``: psi = arg(sum_a p(a) exp(4 i a)) / 4, p(a) = mean power of beam a over the image's range;
- ``profile-c``: the same on the beam's power minus the scan's mean beam (contrast: the same psi, a check);
- ``profile-sq`` / ``profile-hi`` / ``profile-far10``: p(a) = mean squared power / the share of the beam's bins
  above the scan's 95th percentile / mean power from 10 m (variants for a steadier heading);
- ``grad``: from the Cartesian image's gradient orientations, psi = arg(sum (g_x + i g_y)^4 / |g|^2) / 4,
  converted to an azimuth shift (the sign measured on the fly from a turned copy).

Rows: descriptor-alone Recall@1 of each rule, for the queries as rendered and turned by a random heading (seeded);
the canonical heading's disagreement between each query and its nearest map scan (world frame, mod 90 deg); and the
global cosine of a scan and its turned copy (any angle).

Usage:
    python benchmarks/probe_canonical_heading.py --split train-target-boreas --model our-3-boreas-w05
    python benchmarks/probe_canonical_heading.py --protocol confidence-sessions --split train-target-offroad \
        --model our-3-offroad-w05
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from reradar_core.geometry.cartesian import polar_to_cartesian  # noqa: E402
from reradar_core.geometry.heading import turn_scan  # noqa: E402
from reradar_core.io.datasets import load_sequence  # noqa: E402
from reradar_core.model import DescriptorExtractor  # noqa: E402
from reradar_core.training.suites import suite_training_data  # noqa: E402
from reradar_core.training.trainer import recall_at_1_from_descriptors  # noqa: E402

QUARTER = np.pi / 2


def _beam_profile(scan, range_m: float, kind: str) -> np.ndarray:
    r = scan.range_offset_m + scan.range_resolution_m * np.arange(scan.num_range_bins)
    lo = 10.0 if kind == "far10" else 2.0
    q = scan.power[:, (r > lo) & (r <= range_m)].astype(np.float64)
    if kind == "sq":
        return (q ** 2).mean(axis=1)
    if kind == "hi":
        return (q > np.quantile(q, 0.95)).mean(axis=1)
    return q.mean(axis=1)


def psi_profile(scan, range_m: float, contrast: bool, kind: str = "mean") -> float:
    p = _beam_profile(scan, range_m, kind)
    if contrast:
        p = p - p.mean()
    z = np.sum(p * np.exp(4j * scan.azimuths))
    return float(np.angle(z) / 4)


def psi_grad(img: np.ndarray) -> float:
    gx = cv2.Sobel(img, cv2.CV_64F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=3)
    w = img.shape[0]
    c = (w - 1) / 2
    yy, xx = np.mgrid[:w, :w]
    disc = np.hypot(yy - c, xx - c) <= c - 2
    g = (gx + 1j * gy)[disc]
    m = np.abs(g) ** 2
    z = np.sum(np.where(m > 0, g ** 4 / np.where(m > 0, m, 1), 0))
    return float(np.angle(z) / 4)


class Canon:
    def __init__(self, ex: DescriptorExtractor, rule: str) -> None:
        self.ex, self.rule = ex, rule
        self.range_m = ex.cartesian.width_px * ex.cartesian.resolution_m / 2
        self.grad_sign = 0.0
        if rule == "grad":
            self.grad_sign = 1.0

    def shift(self, scan) -> float:
        if self.rule == "none":
            return 0.0
        if self.rule == "profile":
            return -psi_profile(scan, self.range_m, False)
        if self.rule == "profile-c":
            return -psi_profile(scan, self.range_m, True)
        if self.rule in ("profile-sq", "profile-hi", "profile-far10"):
            return -psi_profile(scan, self.range_m, False, self.rule.split("-")[1])
        return self.grad_sign * -psi_grad(polar_to_cartesian(scan, self.ex.cartesian))

    def image(self, scan) -> tuple[np.ndarray, float]:
        s = self.shift(scan)
        return polar_to_cartesian(turn_scan(scan, s), self.ex.cartesian), s


def calibrate_grad_sign(canon: Canon, scan) -> float:
    """+1 or -1 so that the grad rule's shift is equivariant like the profile rule (checked on a 20-deg turn)."""
    t = np.deg2rad(20.0)
    a = psi_grad(polar_to_cartesian(scan, canon.ex.cartesian))
    b = psi_grad(polar_to_cartesian(turn_scan(scan, t), canon.ex.cartesian))
    d_plus = np.angle(np.exp(4j * (b - a - t)))
    d_minus = np.angle(np.exp(4j * (b - a + t)))
    return -1.0 if abs(d_plus) < abs(d_minus) else 1.0


def descriptors(ex: DescriptorExtractor, images: list[np.ndarray]) -> np.ndarray:
    out = []
    for k in range(0, len(images), 16):
        out.append(ex.run_images(np.stack(images[k:k + 16]))[0])
    return np.concatenate(out)


def sessions_protocol(args) -> None:
    """Descriptor-alone Recall@1 of the revisits of a training split's unseen ``confidence`` sessions (every 2nd
    scan) against its domain's map drive: the protocol of the canonical heading's first trial (docs/MODEL.md), with
    the model's own extractor (``ModelConfig.canonical_heading`` off / on), as recorded and turned by a random heading."""
    import dataclasses

    from reradar_core.sim.suites import build_suite
    from reradar_core.training.suites import TRAINING_SPLITS

    data = build_suite(args.split, progress=False)
    bench = build_suite(TRAINING_SPLITS[args.split], progress=False)
    db_seq = bench.load(bench.database[0])
    db_xy = np.asarray(db_seq.poses.poses)[:, :2]
    db_scans = [db_seq.load_scan(i) for i in range(len(db_seq))]
    rng = np.random.default_rng(args.seed)
    for qpath in data.confidence:
        qseq = data.load(qpath)
        idx = np.arange(0, len(qseq), 2)
        q_xy = np.asarray(qseq.poses.poses)[idx, :2]
        q_scans = [qseq.load_scan(int(i)) for i in idx]
        turns = rng.uniform(0, 2 * np.pi, len(q_scans))
        for canonical in (False, True):
            ex = DescriptorExtractor.from_pretrained(args.model)
            ex.config = ex.net.config = dataclasses.replace(ex.config, canonical_heading=canonical)
            t0 = time.perf_counter()
            gd = ex.global_descriptors(db_scans)
            gq = ex.global_descriptors(q_scans)
            gqt = ex.global_descriptors([turn_scan(s, t) for s, t in zip(q_scans, turns, strict=True)])
            r1, nq = recall_at_1_from_descriptors(gd, db_xy, gq, q_xy, bench.radius_m)
            r1t, _ = recall_at_1_from_descriptors(gd, db_xy, gqt, q_xy, bench.radius_m)
            row = {"protocol": "confidence-sessions", "split": args.split, "model": args.model,
                   "session": qpath.name, "canonical_heading": canonical, "revisits": nq,
                   "recall_at_1": round(100 * r1, 2), "recall_at_1_turned": round(100 * r1t, 2),
                   "seconds": round(time.perf_counter() - t0, 1)}
            print(json.dumps(row), flush=True)
            if args.json:
                with open(args.json, "a") as fh:
                    fh.write(json.dumps(row) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--split", default="train-target-boreas")
    ap.add_argument("--model", default="our-3-boreas-w05")
    ap.add_argument("--rules", default="none,profile,profile-c,grad")
    ap.add_argument("--max-scans", type=int, default=200, help="per tail (evenly spaced)")
    ap.add_argument("--seed", type=int, default=0, help="the turned queries' headings")
    ap.add_argument("--json", default=None)
    ap.add_argument("--protocol", choices=["tails", "confidence-sessions"], default="tails",
                    help="tails: the split's validation tails, each --rules rule; confidence-sessions: its unseen "
                         "confidence sessions against the map drive, the shipped rule off / on")
    args = ap.parse_args()
    if args.protocol == "confidence-sessions":
        sessions_protocol(args)
        return
    ex = DescriptorExtractor.from_pretrained(args.model)
    plan = suite_training_data(args.split, progress=False)
    rng = np.random.default_rng(args.seed)
    rows = []
    for db_spec, q_spec in plan.val:
        tails = []
        for spec in (db_spec, q_spec):
            seq = load_sequence(spec.path)
            n = len(seq)
            idx = np.arange(int(n * spec.start), int(n * spec.stop))
            if len(idx) > args.max_scans:
                idx = idx[np.unique(np.linspace(0, len(idx) - 1, args.max_scans).round().astype(int))]
            tails.append(([seq.load_scan(int(i)) for i in idx], np.asarray(seq.poses.poses)[idx]))
        (db_scans, db_pose), (q_scans, q_pose) = tails
        q_turn = rng.uniform(0, 2 * np.pi, len(q_scans))
        d = np.hypot(q_pose[:, None, 0] - db_pose[None, :, 0], q_pose[:, None, 1] - db_pose[None, :, 1])
        nearest = d.argmin(1)
        for rule in args.rules.split(","):
            t0 = time.perf_counter()
            canon = Canon(ex, rule)
            if rule == "grad":
                canon.grad_sign = calibrate_grad_sign(canon, db_scans[0])
            db_img, db_s = zip(*(canon.image(s) for s in db_scans), strict=True)
            q_img, q_s = zip(*(canon.image(s) for s in q_scans), strict=True)
            qt_img, qt_s = zip(*(canon.image(turn_scan(s, t)) for s, t in zip(q_scans, q_turn, strict=True)), strict=True)
            gd, gq, gqt = descriptors(ex, list(db_img)), descriptors(ex, list(q_img)), descriptors(ex, list(qt_img))
            r1, nq = recall_at_1_from_descriptors(gd, db_pose[:, :2], gq, q_pose[:, :2], plan.radius_m)
            r1t, _ = recall_at_1_from_descriptors(gd, db_pose[:, :2], gqt, q_pose[:, :2], plan.radius_m)
            # canonical heading in the world frame: yaw + shift (mod 90 deg); disagreement q vs its nearest map scan
            # (the image is rendered at azimuths + shift, i.e. the sensor turned by shift: world heading yaw + shift).
            wq = q_pose[:, 2] + np.asarray(q_s)
            wd = db_pose[nearest, 2] + np.asarray(db_s)[nearest]
            dis = np.abs(np.angle(np.exp(4j * (wq - wd)))) / 4
            near = d.min(1) <= plan.radius_m
            # turned-copy cosine: query k turned vs as rendered, both through the rule
            cos = np.sum(gq * gqt, 1) / (np.linalg.norm(gq, axis=1) * np.linalg.norm(gqt, axis=1))
            row = {"split": args.split, "model": args.model, "db": db_spec.path.name, "queries": q_spec.path.name,
                   "rule": rule, "n_eval": nq, "recall_at_1": round(100 * r1, 2),
                   "recall_at_1_turned": round(100 * r1t, 2),
                   "heading_disagreement_deg_median": round(float(np.rad2deg(np.median(dis[near]))), 2),
                   "heading_disagreement_deg_p90": round(float(np.rad2deg(np.quantile(dis[near], 0.9))), 2),
                   "turned_copy_cosine_min": round(float(cos.min()), 4),
                   "turned_copy_cosine_mean": round(float(cos.mean()), 4),
                   "seconds": round(time.perf_counter() - t0, 1)}
            rows.append(row)
            print(json.dumps(row), flush=True)
    if args.json:
        with open(args.json, "a") as fh:
            for r in rows:
                fh.write(json.dumps(r) + "\n")


if __name__ == "__main__":
    main()
