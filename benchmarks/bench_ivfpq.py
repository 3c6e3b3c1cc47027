"""Memory and query time of a FAISS IVF-PQ index at city scale (docs/OPERATIONS.md, sizing).

Random unit vectors stand in for the global descriptors (D = 256, the default model's): they give the index's
size and search time, not its recall. One search thread, as in a service replica.

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_ivfpq.py --size 1000000
"""

from __future__ import annotations

import argparse
import os
import time

import faiss
import numpy as np


def unit(rng: np.random.Generator, n: int, d: int) -> np.ndarray:
    x = rng.standard_normal((n, d), dtype=np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return x


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1_000_000)
    ap.add_argument("--dim", type=int, default=256)
    ap.add_argument("--nlist", type=int, default=4096)
    ap.add_argument("--m", type=int, default=32, help="PQ sub-quantizers (bytes per vector at 8 bits)")
    ap.add_argument("--nprobe", type=int, default=16)
    ap.add_argument("--train", type=int, default=100_000)
    ap.add_argument("--queries", type=int, default=2000)
    args = ap.parse_args()
    faiss.omp_set_num_threads(1)
    rng = np.random.default_rng(0)
    quantizer = faiss.IndexFlatIP(args.dim)
    index = faiss.IndexIVFPQ(quantizer, args.dim, args.nlist, args.m, 8, faiss.METRIC_INNER_PRODUCT)
    t0 = time.perf_counter()
    index.train(unit(rng, args.train, args.dim))
    t_train = time.perf_counter() - t0
    t0 = time.perf_counter()
    for start in range(0, args.size, 100_000):
        index.add(unit(rng, min(100_000, args.size - start), args.dim))
    t_add = time.perf_counter() - t0
    size_b = faiss.serialize_index(index).nbytes
    index.nprobe = args.nprobe
    q = unit(rng, args.queries, args.dim)
    lat = []
    for i in range(args.queries):
        t0 = time.perf_counter()
        index.search(q[i:i + 1], 60)
        lat.append(time.perf_counter() - t0)
    ms = np.array(lat) * 1e3
    print(f"IVF{args.nlist},PQ{args.m}x8 D={args.dim} N={args.size:,}: train {t_train:.0f} s, add {t_add:.0f} s, "
          f"index {size_b / 2**20:.1f} MiB ({size_b / args.size:.1f} B/keyframe), top-60 search with nprobe "
          f"{args.nprobe}: p50 {np.percentile(ms, 50):.2f} ms, p99 {np.percentile(ms, 99):.2f} ms "
          f"(1 thread; load average {os.getloadavg()[0]:.2f})")


if __name__ == "__main__":
    main()
