"""Descriptor model speed on CPU: exported network latency (batch 1), batched throughput, full describe().

Usage:
    python benchmarks/bench_model.py [--threads 2] [--repeats 30] [--quick]

Prints a markdown table (the one in docs/BENCHMARKS.md, "Descriptor model speed"). Random weights give the
same speed as trained ones; the shipped default model is timed through ``DescriptorExtractor`` when present.
Measure on a quiet machine: other processes on the two cores inflate every number.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import torch

from reradar_core.io.scan import RadarScan
from reradar_core.model import DescriptorExtractor, DescriptorNet, ModelConfig, available_models
from reradar_core.model.network import fuse_batchnorm


def _median_ms(fn, repeats: int, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return 1000.0 * float(np.median(ts))


def bench_network(cfg: ModelConfig, repeats: int, batch: int = 16) -> tuple[float, float, int]:
    """(batch-1 median ms, batched ms per image, #parameters) of the fused exported network."""
    torch.manual_seed(0)
    net = fuse_batchnorm(DescriptorNet(cfg).eval())
    w = cfg.cartesian_width_px
    x1 = torch.rand(1, 1, w, w)
    xb = torch.rand(batch, 1, w, w)
    with torch.inference_mode():
        t1 = _median_ms(lambda: net(x1), repeats)
        tb = _median_ms(lambda: net(xb), max(3, repeats // 5)) / batch
    return t1, tb, sum(p.numel() for p in DescriptorNet(cfg).parameters())


def _boreas_like_scan(seed: int = 0) -> RadarScan:
    rng = np.random.default_rng(seed)
    power = (rng.random((400, 3360)) ** 6).astype(np.float32)
    return RadarScan.from_power(power, preset="boreas")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--quick", action="store_true", help="only the default configuration")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {args.threads} threads, {platform.processor() or platform.machine()}")
    configs = [ModelConfig()]
    if not args.quick:
        configs = [ModelConfig(width=0.25), ModelConfig(width=0.5), ModelConfig(width=1.0),
                   ModelConfig(cartesian_width_px=200), ModelConfig(backbone="resnet"),
                   ModelConfig(backbone="resnet", width=0.5), ModelConfig(backbone="resnet", width=1.0)]
    print("| model | input | params | batch 1 (ms) | batch 16 (ms / image) |")
    print("|---|---|---|---|---|")
    for cfg in configs:
        t1, tb, n = bench_network(cfg, args.repeats)
        w = cfg.cartesian_width_px
        print(f"| {cfg.model_id} | {w}x{w} | {n / 1e6:.2f} M | {t1:.1f} | {tb:.1f} |")
    names = available_models()
    if names:
        ex = DescriptorExtractor.from_pretrained("default")
        scan = _boreas_like_scan()
        xy = np.random.default_rng(1).uniform(-60, 60, (400, 2))
        t_cart = _median_ms(lambda: ex.cartesian_image(scan), args.repeats)
        t_desc = _median_ms(lambda: ex.describe(scan, landmarks=xy), args.repeats)
        scans = [_boreas_like_scan(s) for s in range(16)]
        lms = [xy] * 16
        t_batch = _median_ms(lambda: ex.describe_batch(scans, landmarks=lms), max(3, args.repeats // 5)) / 16
        print(f"\nshipped default {ex.name} ({ex.model_id}): polar->Cartesian {t_cart:.1f} ms; "
              f"describe() without landmark detection (400 keypoints) {t_desc:.1f} ms per scan; "
              f"describe_batch(16) {t_batch:.1f} ms per scan")


if __name__ == "__main__":
    main()
