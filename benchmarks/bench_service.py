#!/usr/bin/env python3
"""Service benchmarks: POST /localize latency over HTTP, FAISS retrieval on a 100,000-keyframe map,
resident memory per keyframe, what geometric re-ranking adds over plain top-1, and the Localizer offline
(global vs tracking mode along a drive).

    python benchmarks/bench_service.py --all              # everything (a few minutes on 2 cores)
    python benchmarks/bench_service.py --http --requests 100
    python benchmarks/bench_service.py --http --http-map MAP.h5 --http-queries SEQ/radar   # demo + a bigger map
    python benchmarks/bench_service.py --http --http-transport both   # PNG vs the .npy transport, side by side
    python benchmarks/bench_service.py --faiss --memory
    python benchmarks/bench_service.py --rerank --suite smoke
    python benchmarks/bench_service.py --localizer --http-map MAP.h5 --sequences SEQ [SEQ ...]  # global vs tracking

Results print as Markdown and are saved as JSON under the cache (``bench/service``); copy the numbers into
docs/BENCHMARKS.md with the command used.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import platform
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


def _rss_bytes() -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return 0


def _unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def _load_avg() -> str:
    try:
        return " ".join(f"{v:.1f}" for v in os.getloadavg())
    except OSError:
        return "n/a"


# ---------------------------------------------------------------------------------------------- FAISS
def bench_faiss(n: int, dim: int, queries: int, seed: int = 0) -> dict:
    """Per-query search latency (1 thread, k=5) of exact and HNSW indexes over n unit descriptors."""
    from reradar_core.retrieval import GlobalIndex, IndexConfig

    rng = np.random.default_rng(seed)
    # route-like descriptors: a random walk on the sphere (neighbouring places look alike) plus per-scan noise;
    # queries = keyframes seen again with noise of norm 0.3 (a revisit in other weather)
    walk = _unit(np.cumsum(_unit(rng.normal(size=(max(1, n // 20), dim))), axis=0))
    x = _unit(np.repeat(walk, 20, axis=0)[:n] + 0.5 * _unit(rng.normal(size=(n, dim))))
    targets = rng.integers(0, n, queries)
    q = _unit(x[targets] + 0.3 * _unit(rng.normal(size=(queries, dim))))
    out: dict = {"num_keyframes": n, "dim": dim, "queries": queries}
    exact_top1 = None
    for kind in ("flat", "auto", "hnsw"):
        t0 = time.perf_counter()
        idx = GlobalIndex(x, IndexConfig(kind=kind))
        build_s = time.perf_counter() - t0
        lat, cpu = [], []
        top1 = np.empty(queries, np.int64)
        for i in range(queries):
            t, c = time.perf_counter(), time.thread_time()
            ids, _ = idx.search(q[i], 5)
            cpu.append((time.thread_time() - c) * 1e3)  # the search's own CPU time: waits for a core excluded
            lat.append((time.perf_counter() - t) * 1e3)
            top1[i] = ids[0, 0]
        res = {"index": idx.kind, "build_s": build_s, "p50_ms": _pct(lat, 50), "p99_ms": _pct(lat, 99),
               "cpu_p50_ms": _pct(cpu, 50), "cpu_p99_ms": _pct(cpu, 99),
               "mean_ms": float(np.mean(lat)), "index_bytes_per_keyframe": idx.memory_bytes / n}
        if kind == "flat":
            exact_top1 = top1
        else:
            res["top1_agreement_with_exact"] = float(np.mean(top1 == exact_top1))
        out[kind] = res
    return out


# ---------------------------------------------------------------------------------------------- memory
def bench_memory(n: int, dim: int, local_dim: int, keypoints: int, seed: int = 0) -> dict:
    """RSS growth from opening an n-keyframe map (descriptors + poses in RAM, FAISS index built)."""
    from maps.store import MapMetadata, MapWriter
    from reradar_core.features import ScanFeatures

    rng = np.random.default_rng(seed)
    tmp = Path(tempfile.mkdtemp(prefix="reradar-bench-mem-"))
    try:
        path = tmp / "big.h5"
        meta = MapMetadata("bench", "0" * 64, "boreas", 201, 0.64, dim, local_dim, name="bench")
        t0 = time.perf_counter()
        kps = rng.uniform(-80, 80, (keypoints, 2)).astype(np.float32)
        loc = _unit(rng.normal(size=(keypoints, local_dim))).astype(np.float16)
        g = _unit(rng.normal(size=(n, dim)))
        with MapWriter(path, meta) as w:
            for i in range(n):
                w.add(ScanFeatures(g[i], kps, loc, i), np.array([i * 2.0, 0.0, 0.0]))
        write_s = time.perf_counter() - t0
        del g
        gc.collect()
        out = {"num_keyframes": n, "dim": dim, "local_dim": local_dim, "keypoints_per_keyframe": keypoints,
               "file_mb": path.stat().st_size / 1e6, "write_s": write_s}
        for kind in ("flat", "auto"):
            # a fresh process per index kind: RSS deltas in one process are blurred by allocator reuse
            proc = subprocess.run([sys.executable, __file__, "--measure-open", str(path), kind],
                                  capture_output=True, text=True, check=True)
            res = json.loads(proc.stdout.strip().splitlines()[-1])
            res["rss_bytes_per_keyframe"] = res["rss_bytes"] / n
            out[kind] = res
        return out
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# ---------------------------------------------------------------------------------------------- HTTP
def measure_open(path: str, kind: str) -> dict:
    """RSS growth of this (fresh) process from opening the map at ``path`` with index ``kind``."""
    from maps.database import MapDatabase
    from reradar_core.retrieval import IndexConfig

    gc.collect()
    before = _rss_bytes()
    t0 = time.perf_counter()
    db = MapDatabase.open(path, index_config=IndexConfig(kind=kind))
    load_s = time.perf_counter() - t0
    gc.collect()
    after = _rss_bytes()
    t0 = time.perf_counter()
    db.map.read_keyframe(len(db) // 2)
    read_ms = (time.perf_counter() - t0) * 1e3
    return {"index": db.index.kind, "load_s": load_s, "rss_bytes": after - before, "read_keyframe_ms": read_ms}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _navtech_npy(png: bytes) -> bytes:
    """The PNG's pixels as .npy bytes (``scan_layout=navtech``: the same scan without PNG decompression)."""
    import io

    import cv2

    buf = io.BytesIO()
    np.save(buf, cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED))
    return buf.getvalue()


def bench_http(requests: int, warmup: int, threads: int, map_path: Path | None = None,
               queries_dir: Path | None = None, transports: tuple[str, ...] = ("png",)) -> dict:
    """Sequential POST /localize (inline scan, multipart) against `reradar serve` in a subprocess.

    Default: the demo map and its 8 queries. ``map_path`` + ``queries_dir``: another map (e.g. 560 keyframes
    built with `reradar build-map`) and ``requests`` PNG scans evenly spread over a query folder.
    ``transports``: ``png`` and / or ``navtech-npy`` (the PNG's pixels as .npy, ``scan_layout=navtech``); with
    both, each query is sent both ways in turn (side by side on one server) and the second's figures are under
    ``transports``; their answers must agree.
    """
    from maps.paths import DEMO_MAP_PATH, DEMO_QUERIES_DIR
    from service.client import ReRadarClient
    from service.demo import QUERIES_CSV, read_queries_csv

    if queries_dir is not None:
        files = sorted(Path(queries_dir).glob("*.png"))
        pick = np.unique(np.linspace(0, len(files) - 1, max(requests, warmup)).round().astype(int)) if files else []
        blobs = [(files[i].name, files[i].read_bytes()) for i in pick]
        if not blobs:
            raise SystemExit(f"no .png scans in {queries_dir}")
    else:
        truth = read_queries_csv(DEMO_QUERIES_DIR / QUERIES_CSV)
        blobs = [(q.file, (DEMO_QUERIES_DIR / q.file).read_bytes()) for q in truth]
    tmp = Path(tempfile.mkdtemp(prefix="reradar-bench-http-"))
    port = _free_port()
    env = dict(os.environ, RERADAR_MAPS_DIR=str(tmp / "maps"), RERADAR_LOAD_DEMO_MAP="false",
               RERADAR_TORCH_THREADS=str(threads))
    (tmp / "maps").mkdir()
    shutil.copyfile(map_path or DEMO_MAP_PATH, tmp / "maps" / "demo.h5")
    log = open(tmp / "server.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "reradar_cli", "serve", "--port", str(port),
                             "--log-level", "warning"], env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        with ReRadarClient(f"http://127.0.0.1:{port}") as client:
            client.wait_ready(timeout_s=300)
            for i in range(warmup):
                name, data = blobs[i % len(blobs)]
                client.localize("demo", scan_bytes=data, filename=name)
            npys = {name: _navtech_npy(data) for name, data in blobs} if "navtech-npy" in transports else {}
            per: dict[str, tuple[list, dict, dict]] = {t: ([], {}, {}) for t in transports}
            disagree = 0
            for i in range(requests):
                name, data = blobs[i % len(blobs)]
                answers = set()
                for t in transports:
                    lat, stages, statuses = per[t]
                    t0 = time.perf_counter()
                    if t == "navtech-npy":
                        res = client.localize("demo", scan_bytes=npys[name], filename=Path(name).stem + ".npy",
                                              scan_layout="navtech")
                    else:
                        res = client.localize("demo", scan_bytes=data, filename=name)
                    lat.append((time.perf_counter() - t0) * 1e3)
                    statuses[res.status] = statuses.get(res.status, 0) + 1
                    for k, v in res.timings_ms.items():
                        stages.setdefault(k, []).append(v)
                    answers.add((res.status, res.keyframe.keyframe_id if res.keyframe else None,
                                 None if res.pose is None else (res.pose.x_m, res.pose.y_m, res.pose.yaw_deg)))
                disagree += len(answers) > 1
            lat, stages, statuses = per[transports[0]]
            others = {t: {"inline_p50_ms": _pct(per[t][0], 50), "inline_p99_ms": _pct(per[t][0], 99),
                          "server_total_p50_ms": _pct(per[t][1]["total_ms"], 50),
                          "server_total_p99_ms": _pct(per[t][1]["total_ms"], 99),
                          "server_stage_mean_ms": {k: float(np.mean(v)) for k, v in sorted(per[t][1].items())},
                          "statuses": per[t][2]} for t in transports[1:]}
            sid = client.upload_scan(scan_bytes=blobs[0][1], filename=blobs[0][0], map_id="demo").scan_id
            lat_ref = []
            for _ in range(min(requests, 50)):
                t0 = time.perf_counter()
                client.localize("demo", scan_id=sid)
                lat_ref.append((time.perf_counter() - t0) * 1e3)
            server_rss = 0
            try:
                with open(f"/proc/{proc.pid}/status") as fh:
                    server_rss = next(int(ln.split()[1]) * 1024 for ln in fh if ln.startswith("VmRSS:"))
            except (OSError, StopIteration):
                pass
        return {
            "map": str(map_path or DEMO_MAP_PATH), "queries": str(queries_dir or DEMO_QUERIES_DIR),
            "requests": requests, "torch_threads": threads, "statuses": statuses,
            "load_avg": _load_avg(),
            "inline_p50_ms": _pct(lat, 50), "inline_p99_ms": _pct(lat, 99), "inline_mean_ms": float(np.mean(lat)),
            "server_total_p50_ms": _pct(stages["total_ms"], 50), "server_total_p99_ms": _pct(stages["total_ms"], 99),
            "by_scan_id_p50_ms": _pct(lat_ref, 50), "by_scan_id_p99_ms": _pct(lat_ref, 99),
            "server_stage_mean_ms": {k: float(np.mean(v)) for k, v in sorted(stages.items())},
            "server_stage_p99_ms": {k: _pct(v, 99) for k, v in sorted(stages.items())},
            "server_rss_mb": server_rss / 1e6,
            "transport": transports[0], "transports": others, "answers_differ_between_transports": disagree,
        }
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()
        shutil.rmtree(tmp, ignore_errors=True)


# ---------------------------------------------------------------------------------------------- localizer
def bench_localizer(map_path: Path, sequences: list[Path], every: int, odometry_noise: float, seed: int = 0,
                    model: str = "default") -> dict:
    """The ``Localizer`` offline (features precomputed; no HTTP, no decoding) on every scan of each query
    sequence: global localization with verification stopping at the localized bar (the default) and with all
    ``verify_k`` verified, and tracking mode through the drive with the ground-truth motion (seeded noise of
    ``odometry_noise`` x step) as odometry. Success: 20 m / 10 degrees (the paper's); ``outside_2m_2deg``
    counts the localized answers farther off than a vehicle can use."""
    import torch
    from tqdm import tqdm

    from maps.database import MapDatabase
    from reradar_core.benchmark.metrics import covariance_report
    from reradar_core.evaluation import localization_errors, localization_success, pose_error, radius_for
    from reradar_core.geometry.se2 import relative_pose
    from reradar_core.io.datasets import load_sequence
    from reradar_core.localization import LocalizationConfig, PosePrior
    from reradar_core.model import DescriptorExtractor
    from service.core.blas import limit_blas_threads
    from service.follow import POSE_ROTATION_DEG, POSE_TRANSLATION_M, noisy_odometry

    torch.set_num_threads(1)
    limit_blas_threads(1)
    ext = DescriptorExtractor.from_pretrained(model)  # the map's model (a mismatch is refused on open)
    db = MapDatabase.open(map_path, ext.model_id, ext.weights_sha256, keyframe_cache_size=None, preload=True)
    out: dict = {"map": str(map_path), "num_keyframes": len(db), "odometry_noise": odometry_noise}

    def judge(res, gt, radius_m: float) -> str:  # noqa: ANN001
        """``ok`` (within 2 m / 2 deg), ``off`` (the paper's success only: e_t < R, e_r < 10 deg), ``wrong``,
        ``not``."""
        if not res.localized:
            return "not"
        e_t, e_r = localization_errors(res.T_map_query[None], np.asarray(gt)[None])
        if e_t[0] <= POSE_TRANSLATION_M and e_r[0] <= POSE_ROTATION_DEG:
            return "ok"
        return "off" if localization_success(e_t, e_r, radius_m)[0] else "wrong"

    for seq_dir in sequences:
        seq = load_sequence(seq_dir)
        idx = np.arange(0, len(seq), every)
        feats = [ext.describe(seq.load_scan(int(i))) for i in tqdm(idx, desc=f"features {seq.name}")]
        gts = seq.mid_sweep_poses()[idx]  # answers are mid-sweep poses
        radius_m = radius_for(seq.preset.name)
        res_seq: dict = {"scans": len(idx), "radius_m": radius_m}
        modes = {"global": LocalizationConfig(), "global_verify_all": LocalizationConfig(stop_verify_ratio=None)}
        for name, cfg in modes.items():
            lat, outc = [], []
            for f, gt in zip(feats, gts, strict=True):
                t0 = time.perf_counter()
                res = db.localize(f, cfg)
                lat.append((time.perf_counter() - t0) * 1e3)
                outc.append(judge(res, gt, radius_m))
            res_seq[name] = _summarise(lat, outc)
        rng = np.random.default_rng(seed)
        lat, outc, kinds, conf, prior = [], [], [], [], None
        cov_err: dict[str, list[np.ndarray]] = {"global": [], "tracking": []}  # right answers' errors, covariances
        cov_mat: dict[str, list[np.ndarray]] = {"global": [], "tracking": []}
        for n, (f, gt) in enumerate(zip(feats, gts, strict=True)):
            if prior is not None:
                prior = prior.moved(noisy_odometry(relative_pose(gts[n - 1], gt), odometry_noise, rng),
                                    timestamp_us=f.timestamp_us)  # as the service's sessions: a speed for the pose
            t0 = time.perf_counter()
            res = db.track(f, prior) if prior is not None else db.localize(f)
            lat.append((time.perf_counter() - t0) * 1e3)
            outc.append(judge(res, gt, radius_m))
            kinds.append("tracking" if res.mode == "tracking" else ("lost" if res.tracking_lost else "global"))
            conf.append(float(res.confidence) if res.confidence is not None else math.nan)
            if outc[-1] in ("ok", "off") and res.pose_covariance is not None:
                cov_err["tracking" if res.mode == "tracking" else "global"].append(pose_error(gt, res.T_map_query))
                cov_mat["tracking" if res.mode == "tracking" else "global"].append(res.pose_covariance)
            if res.localized:
                prior = PosePrior(res.T_map_query, 0.5, math.radians(1.0), f.timestamp_us)
        summary = _summarise(lat, outc)
        tracked = np.array(kinds) == "tracking"
        summary["tracked_scans"] = int(tracked.sum())
        summary["lost_scans"] = int(np.sum(np.array(kinds) == "lost"))
        summary["tracked_p50_ms"] = _pct(list(np.asarray(lat)[tracked]), 50) if tracked.any() else math.nan
        summary["wrong_from_tracking"] = int(np.sum(tracked & (np.array(outc) == "wrong")))
        summary["outside_2m_2deg_from_tracking"] = int(np.sum(tracked & np.isin(outc, ["off", "wrong"])))
        conf_tracked = np.asarray(conf)[tracked]
        summary["tracked_confidence_p5"] = _pct(list(conf_tracked), 5) if tracked.any() else math.nan
        summary["tracked_below_bar"] = int(np.sum(conf_tracked < LocalizationConfig().effective_min_confidence))
        # the pose covariance against the right answers' errors, tracked and global answers apart
        summary["pose_covariance"] = {k: covariance_report(np.array(cov_err[k]), np.array(cov_mat[k]))
                                      for k in cov_err if cov_err[k]}
        res_seq["tracking"] = summary
        res_seq["tracked_p50_over_global_p50"] = summary["tracked_p50_ms"] / res_seq["global"]["p50_ms"]
        out[seq.name] = res_seq
    db.close()
    return out


def _summarise(lat: list[float], outcomes: list[str]) -> dict:
    o = np.asarray(outcomes)
    return {"success_rate": float(np.mean((o == "ok") | (o == "off"))), "wrong": int(np.sum(o == "wrong")),
            "outside_2m_2deg": int(np.sum((o == "off") | (o == "wrong"))),
            "not_localized": int(np.sum(o == "not")), "p50_ms": _pct(lat, 50), "p99_ms": _pct(lat, 99),
            "mean_ms": float(np.mean(lat))}


# ---------------------------------------------------------------------------------------------- re-ranking
def bench_rerank(suite_name: str, threads: int, top_k: int, ransac_threshold_m: float | None = None) -> dict:
    """Success rate of plain top-1 (retrieve, verify only the best) vs top-k geometric re-ranking."""
    import torch
    from tqdm import tqdm

    from maps.build import build_map_from_sequence
    from maps.database import MapDatabase
    from reradar_core.evaluation import localization_errors, localization_success
    from reradar_core.localization import LocalizationConfig
    from reradar_core.model import DescriptorExtractor
    from reradar_core.paths import cache_dir
    from reradar_core.sim.suites import build_suite
    from service.core.blas import limit_blas_threads

    torch.set_num_threads(threads)
    limit_blas_threads(1)
    suite = build_suite(suite_name, progress=True)
    ext = DescriptorExtractor.from_pretrained()
    map_path = cache_dir("bench", "service") / f"{suite_name}-{ext.weights_sha256[:12]}.h5"
    if not map_path.exists():
        build_map_from_sequence(suite.database[0], map_path, ext, layout=suite.layout, preset=suite.preset,
                                show_progress=True)
    db = MapDatabase.open(map_path, ext.model_id, ext.weights_sha256)
    radius = suite.radius_m
    out: dict = {"suite": suite_name, "radius_m": radius, "top_k": top_k, "num_keyframes": len(db)}
    from reradar_core.matching import RansacConfig

    ransac = RansacConfig() if ransac_threshold_m is None else RansacConfig(inlier_threshold_m=ransac_threshold_m)
    out["ransac_inlier_threshold_m"] = ransac.inlier_threshold_m
    modes = {"top1": LocalizationConfig(top_k=top_k, rerank=False, ransac=ransac),
             "rerank": LocalizationConfig(top_k=top_k, ransac=ransac)}
    counts = {m: {"localized": 0, "success": 0, "correct_place": 0, "et": [], "er": []} for m in modes}
    retrieval_top1_correct = 0
    n = 0
    for qpath in suite.queries:
        seq = suite.load(qpath)
        for i in tqdm(range(len(seq)), desc=f"queries {qpath.name}"):
            feat = ext.describe(seq.load_scan(i))
            gt = seq.mid_sweep_poses()[i]  # answers are mid-sweep poses
            n += 1
            for mode, cfg in modes.items():
                retr, res = db.retrieve(feat.global_descriptor, cfg.top_k), db.localize(feat, cfg)
                if mode == "top1" and retr:
                    retrieval_top1_correct += np.hypot(*(retr[0].T_map_keyframe[:2] - gt[:2])) <= radius
                c = counts[mode]
                if res.best is not None and np.hypot(*(res.best.T_map_keyframe[:2] - gt[:2])) <= radius:
                    c["correct_place"] += 1
                if res.localized and res.T_map_query is not None:
                    c["localized"] += 1
                    e_t, e_r = localization_errors(res.T_map_query[None], np.asarray(gt)[None])
                    et, er = float(e_t[0]), float(e_r[0])
                    if localization_success(e_t, e_r, radius)[0]:
                        c["success"] += 1
                        c["et"].append(et)
                        c["er"].append(er)
    out["num_queries"] = n
    out["retrieval_recall_at_1"] = retrieval_top1_correct / max(n, 1)
    for mode, c in counts.items():
        out[mode] = {"localized_fraction": c["localized"] / max(n, 1), "success_rate": c["success"] / max(n, 1),
                     "chosen_keyframe_correct": c["correct_place"] / max(n, 1),
                     "mean_translation_error_m": float(np.mean(c["et"])) if c["et"] else math.nan,
                     "mean_rotation_error_deg": float(np.mean(c["er"])) if c["er"] else math.nan}
    db.close()
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--all", action="store_true")
    p.add_argument("--http", action="store_true")
    p.add_argument("--faiss", action="store_true")
    p.add_argument("--memory", action="store_true")
    p.add_argument("--rerank", action="store_true")
    p.add_argument("--requests", type=int, default=100)
    p.add_argument("--http-map", type=Path, default=None, help="--http against this map instead of the demo map")
    p.add_argument("--http-queries", type=Path, default=None, help="folder of query PNGs for --http-map")
    p.add_argument("--http-transport", choices=("png", "navtech-npy", "both"), default="png",
                   help="--http on the demo map: send PNGs, the PNGs' pixels as .npy (scan_layout=navtech), or "
                        "each query both ways in turn")
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--threads", type=int, default=1, help="torch threads of the service")
    p.add_argument("--keyframes", type=int, default=100_000)
    p.add_argument("--dim", type=int, default=256, help="global descriptor length (the default model's D)")
    p.add_argument("--local-dim", type=int, default=32)
    p.add_argument("--queries", type=int, default=1000)
    p.add_argument("--suite", default="smoke")
    p.add_argument("--top-k", type=int, default=5)
    p.add_argument("--ransac-threshold-m", type=float, default=None, help="RANSAC inlier threshold (default: RansacConfig)")
    p.add_argument("--localizer", action="store_true", help="offline Localizer: global vs tracking on --http-map")
    p.add_argument("--sequences", type=Path, nargs="*", default=[], help="--localizer: query sequence folders")
    p.add_argument("--every", type=int, default=1, help="--localizer: use every n-th scan")
    p.add_argument("--odometry-noise", type=float, default=0.05, help="--localizer: odometry noise / step")
    p.add_argument("--model", default="default", help="--localizer: the descriptor model the map was built with")
    p.add_argument("--measure-open", nargs=2, metavar=("MAP", "KIND"), help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.measure_open:
        print(json.dumps(measure_open(*args.measure_open)))
        return 0
    results: dict = {"host": platform.node(), "cpus": os.cpu_count(), "load_avg_start": _load_avg(),
                     "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    if args.all or args.faiss:
        results["faiss"] = bench_faiss(args.keyframes, args.dim, args.queries)
    if args.all or args.memory:
        results["memory"] = bench_memory(args.keyframes, args.dim, args.local_dim, keypoints=8)
    if args.all or args.http:
        if (args.http_map is None) != (args.http_queries is None):
            p.error("--http-map and --http-queries go together")
        transports = ("png", "navtech-npy") if args.http_transport == "both" else (args.http_transport,)
        results["http"] = bench_http(args.requests, args.warmup, args.threads,  # the demo map
                                     transports=transports)
        if args.http_map is not None:  # and the bigger map in the same run: the ratios are the targets
            big = bench_http(args.requests, args.warmup, args.threads, args.http_map, args.http_queries)
            results["http_map"] = big
            results["ratios"] = {
                "map_p50_over_demo_p50": big["inline_p50_ms"] / results["http"]["inline_p50_ms"],
                "map_p99_over_map_p50": big["inline_p99_ms"] / big["inline_p50_ms"],
                "demo_p99_over_demo_p50": results["http"]["inline_p99_ms"] / results["http"]["inline_p50_ms"]}
    if args.localizer:
        if args.http_map is None or not args.sequences:
            p.error("--localizer needs --http-map MAP.h5 and --sequences SEQ [SEQ ...]")
        results["localizer"] = bench_localizer(args.http_map, args.sequences, args.every, args.odometry_noise,
                                           model=args.model)
    if args.all or args.rerank:
        results["rerank"] = bench_rerank(args.suite, args.threads, args.top_k, args.ransac_threshold_m)
    results["load_avg_end"] = _load_avg()
    from reradar_core.paths import cache_dir

    out = cache_dir("bench", "service") / f"bench-{time.strftime('%Y%m%dT%H%M%S')}.json"
    out.write_text(json.dumps(results, indent=2))
    print(json.dumps(results, indent=2))
    print(f"saved {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
