"""Global-descriptor cosine under arbitrary yaw rotation, with and without the sensor-disc mask.

For each scan and yaw theta (default 5...355 deg, step 5) the rotated Cartesian image is rendered from the
polar scan with its azimuths shifted by theta (``geometry.heading.turn_scan``: exact for any angle up to
the polar-to-Cartesian interpolation), and the cosine between the global descriptors of the rotated and the
unrotated scan is reported (min / mean over scans and angles), for each disc-mask variant:

- ``none``: NetVLAD over all F' cells (the behaviour before ``ModelConfig.disc_mask``);
- ``fmap``: only F' cells inside the inscribed circle (``disc_mask=True``, the default);
- ``fmap+input``: also the input image zeroed outside the circle (``disc_mask_input=True``);
- ``fmap+ch``: the F' mask and the canonical heading (``canonical_heading=True``, an option, off by default;
  the other variants switch it off).

With ``--angles`` the yaws are the given ones and a per-angle table is printed, with a reference row: the
cosine between consecutive scans of the folder (the next frame, same heading; on the real Oxford scans 1.6-2.5 m
of driving), i.e. how far a small move shifts the same descriptor (docs/MODEL.md, "What the whitened cosine
measures").

Usage:
    python scripts/rotation_invariance.py --scans PATH/radar --models our-3-boreas our-1 [--limit 8] [--json f]
    python scripts/rotation_invariance.py --scans PATH/radar --models our-3-boreas --variants fmap \
        --angles 0.1 0.25 0.5 1 2 5 45 90
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path[:0] = [str(Path(__file__).resolve().parent), str(Path(__file__).resolve().parents[1])]


from reradar_core.geometry.heading import turn_scan  # noqa: E402
from reradar_core.io.scan import load_scan  # noqa: E402
from reradar_core.model import DescriptorExtractor  # noqa: E402

VARIANTS = {"none": (False, False, False), "fmap": (True, False, False), "fmap+input": (True, True, False),
            "fmap+ch": (True, False, True)}


def set_disc_mask(ex: DescriptorExtractor, fmap: bool, image: bool, canonical: bool = True) -> None:
    """Switch the (parameter-free) disc masks and the canonical heading of a loaded extractor in place."""
    cfg = dataclasses.replace(ex.config, disc_mask=fmap, disc_mask_input=image, canonical_heading=canonical)
    ex.config = cfg
    ex.net.config = cfg


@torch.inference_mode()
def descriptors(ex: DescriptorExtractor, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(global descriptors (B, D), raw NetVLAD vectors (B, K*C)) of (B, W, W) images, masks as configured."""
    x = ex.net.mask_input(torch.from_numpy(np.asarray(images, np.float32))[:, None])
    fmap = ex.net.backbone(x)
    return ex.net.aggregate(fmap).numpy(), ex.net.vlad(fmap).numpy()


def _cos(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a * b).sum(1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))


def rotation_cosines(ex: DescriptorExtractor, scans: list, thetas_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(len(scans), len(thetas)) cosines, rotated vs unrotated: (global descriptor, raw NetVLAD vector). The images
    are the extractor's own (``cartesian_image``: at the canonical heading when the model uses it)."""
    g0, v0 = descriptors(ex, np.stack([ex.cartesian_image(s) for s in scans]))
    out = np.empty((len(scans), len(thetas_deg)))
    raw = np.empty_like(out)
    for j, th in enumerate(thetas_deg):
        g, v = descriptors(ex, np.stack([ex.cartesian_image(turn_scan(s, np.deg2rad(th))) for s in scans]))
        out[:, j], raw[:, j] = _cos(g, g0), _cos(v, v0)
    return out, raw


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", required=True, help="folder of polar PNG scans")
    ap.add_argument("--preset", default=None,
                    help="radar preset of the scans (needed for 3,360-bin scans: boreas, boreas-2021 or mulran)")
    ap.add_argument("--models", nargs="+", default=["our-3-boreas", "our-1"])
    ap.add_argument("--limit", type=int, default=11)
    ap.add_argument("--stride", type=int, default=1, help="take every n-th scan of the folder")
    ap.add_argument("--step", type=float, default=5.0)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS))
    ap.add_argument("--angles", type=float, nargs="+", default=None,
                    help="these yaws (deg) instead of the --step grid, with a per-angle table and a next-frame row")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    paths = sorted(Path(args.scans).glob("*.png"))[:: args.stride][: args.limit]
    if not paths:
        raise SystemExit(f"no .png scans in {args.scans}")
    scans = [load_scan(p, args.preset) for p in paths]
    thetas = np.asarray(args.angles, float) if args.angles else np.arange(args.step, 360.0, args.step)
    results = {}
    for name in args.models:
        ex = DescriptorExtractor.from_pretrained(name)
        for var in args.variants:
            set_disc_mask(ex, *VARIANTS[var])
            c, raw = rotation_cosines(ex, scans, thetas)
            per_theta = c.mean(0)
            non90 = np.mod(thetas, 90) != 0
            results[f"{name}/{var}"] = {"min": float(c.min()), "mean": float(c.mean()),
                                        "raw_netvlad_min": float(raw.min()), "raw_netvlad_mean": float(raw.mean()),
                                        "min_at_deg": float(thetas[int(np.argmin(c.min(0)))]),
                                        "mean_non90": float(c[:, non90].mean()),
                                        "per_theta_mean": per_theta.round(5).tolist()}
            steps90 = f"{c[:, ~non90].min():.5f}" if (~non90).any() else "-"
            print(f"{name:14s} {var:11s} scans {len(scans)}: min {c.min():.4f} at {thetas[np.argmin(c.min(0))]:.0f} "
                  f"deg, mean {c.mean():.4f}, 90-deg steps min {steps90}; raw NetVLAD min {raw.min():.4f} "
                  f"mean {raw.mean():.4f}", flush=True)
            if args.angles:
                print("| yaw (deg) | descriptor cosine min / mean | raw NetVLAD min / mean |\n|---|---|---|")
                for j, th in enumerate(thetas):
                    print(f"| {th:g} | {c[:, j].min():.3f} / {c[:, j].mean():.3f} | {raw[:, j].min():.3f} / "
                          f"{raw[:, j].mean():.3f} |")
                g, v = descriptors(ex, np.stack([ex.cartesian_image(sc) for sc in scans]))
                nxt, nxt_raw = _cos(g[1:], g[:-1]), _cos(v[1:], v[:-1])
                print(f"| next frame, same heading | {nxt.min():.3f} / {nxt.mean():.3f} | {nxt_raw.min():.3f} / "
                      f"{nxt_raw.mean():.3f} |", flush=True)
                results[f"{name}/{var}"]["next_frame"] = {"min": float(nxt.min()), "mean": float(nxt.mean()),
                                                          "raw_min": float(nxt_raw.min()),
                                                          "raw_mean": float(nxt_raw.mean())}
    if args.json:
        Path(args.json).write_text(json.dumps({"scans": [p.name for p in paths], "thetas": thetas.tolist(),
                                               "results": results}, indent=2))


if __name__ == "__main__":
    main()
