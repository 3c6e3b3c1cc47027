"""Controlled yaw-rotation evaluation of F' (paper, Sec. "Rotation Equivariance Analysis", Fig. yaw_consistency).

For each scan I and yaw theta in [0, 360) deg (5 deg steps) the rotated image R_theta I is rendered exactly from
the polar scan (azimuths shifted by theta, so no corner is lost), F_theta = f(R_theta I) is inversely aligned
(F~ = R_-theta F_theta, bilinear on F' cells, 8 px = 5.12 m each) and compared with F = f(I):
S(theta) = mean over scans and over F' cells inside the inscribed disk of cos(F(p), F~(p)).

Usage:
    python scripts/yaw_consistency.py --scans ../shared/data/real-oxford/radar --models our-3-boreas \
        our-3-boreas-resnet --plot docs/img/model_yaw_consistency.png --json yaw.json
    (--scans may also be a simulated sequence folder's radar/ directory; --limit caps the scan count)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from reradar_core.geometry.cartesian import polar_to_cartesian
from reradar_core.geometry.heading import turn_scan
from reradar_core.io.scan import load_scan
from reradar_core.model import DescriptorExtractor
from reradar_core.training.data import crop_view


def rotated_image(scan, ex: DescriptorExtractor, theta: float) -> np.ndarray:
    """Cartesian image of the scan seen by a sensor yawed by ``theta`` (rad, counter-clockwise).

    A sensor turned left by theta sees a point at azimuth a (clockwise) at azimuth a + theta.
    """
    return polar_to_cartesian(turn_scan(scan, theta), ex.cartesian)


def consistency_curve(ex: DescriptorExtractor, scans: list, step_deg: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    thetas = np.arange(0.0, 360.0, step_deg)
    f0 = np.stack([ex.run_images(polar_to_cartesian(s, ex.cartesian)[None])[1][0] for s in scans])  # (S,C,h,h)
    h = f0.shape[-1]
    c = (h - 1) / 2
    rr, cc = np.meshgrid(np.arange(h), np.arange(h), indexing="ij")
    disk = np.hypot(rr - c, cc - c) <= c - 1.0
    cell_m = ex.config.stride * ex.cartesian.resolution_m
    out = []
    for th in thetas:
        t = np.deg2rad(th)
        imgs = np.stack([rotated_image(s, ex, t) for s in scans])
        ft = ex.run_images(imgs)[1]
        cos = []
        for i in range(len(scans)):
            # F~(p) = F_theta(R(-theta) p): crop_view with T = (0, 0, -theta) samples its input at R(-theta) p'
            al = np.stack([crop_view(ch, h, cell_m, np.array([0.0, 0.0, -t])) for ch in ft[i]])
            a, b = f0[i][:, disk], al[:, disk]
            num = (a * b).sum(0)
            den = np.linalg.norm(a, axis=0) * np.linalg.norm(b, axis=0)
            ok = den > 1e-12
            cos.append(float(np.mean(num[ok] / den[ok])))
        out.append(float(np.mean(cos)))
    return thetas, np.array(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", required=True, help="folder of polar PNG scans")
    ap.add_argument("--preset", default=None,
                    help="radar preset of the scans (needed for 3,360-bin scans: boreas, boreas-2021 or mulran)")
    ap.add_argument("--models", nargs="+", default=["default"])
    ap.add_argument("--limit", type=int, default=11)
    ap.add_argument("--step", type=float, default=5.0)
    ap.add_argument("--plot", default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    paths = sorted(Path(args.scans).glob("*.png"))[: args.limit]
    if not paths:
        raise SystemExit(f"no .png scans in {args.scans}")
    scans = [load_scan(p, args.preset) for p in paths]
    results = {}
    for name in args.models:
        ex = DescriptorExtractor.from_pretrained(name)
        th, s = consistency_curve(ex, scans, args.step)
        results[name] = {"model_id": ex.model_id, "theta_deg": th.tolist(), "S": s.tolist(),
                         "min": float(s.min()), "mean": float(s.mean()),
                         "min_at_deg": float(th[int(np.argmin(s))])}
        print(f"{name} ({ex.model_id}) on {len(scans)} scans: min S = {s.min():.4f} at {th[np.argmin(s)]:.0f} deg, "
              f"mean {s.mean():.4f}; S(45) = {s[np.argmin(np.abs(th - 45))]:.4f}, S(90) = "
              f"{s[np.argmin(np.abs(th - 90))]:.4f}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 3.5))
        for name, r in results.items():
            ax.plot(r["theta_deg"], r["S"], label=f"{name} ({r['model_id'].split('-')[0]})")
        ax.set_xlabel("yaw rotation theta (deg)")
        ax.set_ylabel("mean cosine consistency S(theta)")
        ax.set_xlim(0, 360)
        ax.set_xticks(range(0, 361, 45))
        ax.grid(alpha=0.3)
        ax.legend()
        ax.set_title(f"F' consistency under yaw, {len(scans)} scans from {Path(args.scans).parent.name}")
        fig.tight_layout()
        Path(args.plot).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(args.plot, dpi=120)


if __name__ == "__main__":
    main()
