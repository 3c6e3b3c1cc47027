"""Descriptor model speed on CPU: exported network latency (batch 1), batched throughput, full describe().

Usage:
    python benchmarks/bench_model.py [--threads 2] [--repeats 30] [--quick]
    python benchmarks/bench_model.py --threads 1 --runtimes our-3-boreas-w05,our-3-boreas [--rounds 4]
    python benchmarks/bench_model.py --threads 1 --runtimes our-3-boreas-w05 --views near,far

``--runtimes`` times the named shipped models' networks through ``DescriptorExtractor.run_images`` in ONNX Runtime
and in torch (``reradar_core.model.runtime``), alternating the two round by round in one process, and prints the
medians and the torch / ONNX ratio; ``--views near,far`` also times ReRadar's far view (the same weights on 257 px,
``DescriptorExtractor.with_view``; ONNX Runtime runs it when the graph's image size is free, since session 34).

Prints a markdown table (the one in docs/BENCHMARKS.md, "Descriptor model speed"). Random weights give the
same speed as trained ones; the shipped default model is timed through ``DescriptorExtractor`` when present.
Measure on a quiet machine: other processes on the two cores inflate every number.
"""

from __future__ import annotations

import argparse
import os
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


def bench_runtimes(names: list[str], repeats: int, rounds: int, batch: int = 16,
                   views: tuple[str, ...] = ("near",)) -> None:
    """Per model and view: batch-1 and batch-``batch`` network time in ONNX Runtime and torch, alternating round by
    round. ``views``: "near" (the trained input) and/or "far" (``FarViewConfig``'s 257 px, ``with_view``)."""
    from reradar_core.localization.far_view import FarViewConfig

    print("| model | view | runtime | batch 1 (ms) | batch 16 (ms / image) | torch / ONNX, batch 1 | "
          "torch / ONNX, batch 16 |")
    print("|---|---|---|---|---|---|---|")
    for name, view in ((n, v) for n in names for v in views):
        exs = {rt: DescriptorExtractor.from_pretrained(name, runtime=rt) for rt in ("onnx", "torch")}
        if view == "far":
            exs = {rt: ex.with_view(FarViewConfig().cartesian) for rt, ex in exs.items()}
        if exs["onnx"].runtime != "onnx":
            print(f"| {name} | {view} | (no ONNX graph of a free image size: torch only) | | | | |")
        w = exs["torch"].cartesian.width_px
        rng = np.random.default_rng(0)
        x1, xb = rng.random((1, w, w), dtype=np.float32), rng.random((batch, w, w), dtype=np.float32)
        t1: dict[str, list[float]] = {rt: [] for rt in exs}
        tb: dict[str, list[float]] = {rt: [] for rt in exs}
        for _ in range(rounds):
            for rt, ex in exs.items():
                t1[rt].append(_median_ms(lambda ex=ex, x=x1: ex.run_images(x), repeats))
                tb[rt].append(_median_ms(lambda ex=ex, x=xb: ex.run_images(x), max(3, repeats // 5)) / batch)
        m1 = {rt: float(np.median(v)) for rt, v in t1.items()}
        mb = {rt: float(np.median(v)) for rt, v in tb.items()}
        r1 = [a / b for a, b in zip(t1["torch"], t1["onnx"], strict=True)]
        rb = [a / b for a, b in zip(tb["torch"], tb["onnx"], strict=True)]
        for rt in exs:
            ratios = (f"{np.median(r1):.2f} ({min(r1):.2f}-{max(r1):.2f}) | {np.median(rb):.2f} "
                      f"({min(rb):.2f}-{max(rb):.2f})") if rt == "onnx" else " | "
            print(f"| {name} | {view} ({w} px) | {rt} | {m1[rt]:.2f} | {mb[rt]:.2f} | {ratios} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--quick", action="store_true", help="only the default configuration")
    ap.add_argument("--runtimes", default="", help="comma-separated shipped models: time ONNX Runtime against torch")
    ap.add_argument("--rounds", type=int, default=4, help="alternating rounds for --runtimes")
    ap.add_argument("--views", default="near", help="for --runtimes: near and/or far (comma-separated)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {args.threads} threads, {platform.processor() or platform.machine()}, "
          f"load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    if args.runtimes:
        views = tuple(v for v in args.views.split(",") if v)
        if not views or set(views) - {"near", "far"}:
            ap.error(f"--views takes near and/or far, got {args.views!r}")
        bench_runtimes([n for n in args.runtimes.split(",") if n], args.repeats, args.rounds, views=views)
        return
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
