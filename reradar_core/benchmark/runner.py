"""The benchmark runner: every method on the same database / query sequences, paper metrics, JSON + per-query
arrays for the report and the plots.

Stages (each a plain function): ``prepare_sequence`` (prepared records, cached on disk, each scan read once
for all methods) -> ``evaluate_method`` (fit on the database, describe, retrieve / localize every query) ->
``metrics.summarise``. ``run_benchmark`` wires them for a list of (database, query) pairs and also runs the
rotation stress test (the same queries turned by a random heading each).

Per-query arrays are written to a staging folder inside the output folder (``per_query.staging``) and replace
the earlier run's ``per_query/*/*.npz`` only when the run completes (``commit_per_query``): a run that fails or
is interrupted leaves the earlier results.json, results.md and their per-query files as they were.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from collections.abc import Sequence as Seq
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from reradar_core.baselines.base import PlaceRecognitionMethod, Prepared
from reradar_core.benchmark.cache import FeatureCache, sequence_key
from reradar_core.benchmark.metrics import (
    QueryOutcome,
    covariance_calibration,
    make_outcome,
    retrieval_correct,
    summarise,
)
from reradar_core.benchmark.rotation import heading_offsets, rotate_pose, rotate_scan
from reradar_core.errors import ConfigError
from reradar_core.geometry.se2 import compose
from reradar_core.io.datasets import Sequence

__all__ = ["BenchPair", "BenchConfig", "PreparedSet", "prepare_sequence", "evaluate_method", "run_benchmark",
           "sr_rule", "total_steps", "clear_per_query", "commit_per_query", "discard_per_query_staging",
           "min_database_scans", "check_database_sizes", "PER_QUERY_DIR", "PER_QUERY_STAGING_DIR"]

logger = logging.getLogger(__name__)

#: Folder of the per-query arrays inside the output folder (``<pair>/<method>.npz``).
PER_QUERY_DIR = "per_query"
#: Where a running benchmark writes them until it completes (same file system: each file moves by a rename).
PER_QUERY_STAGING_DIR = "per_query.staging"


@dataclass
class BenchPair:
    """One evaluation: a query sequence against a database (reference) sequence.

    Attributes:
        name: label of the pair in the results (the query sequence's name by default).
        database: the reference run (already subsampled, e.g. every 5th scan).
        query: the query run (already subsampled).
        split: for a single-session split, where the sequence was cut (``benchmark.suites.split_pair``);
            None for separate database / query runs.
    """

    name: str
    database: Sequence
    query: Sequence
    split: dict[str, Any] | None = None


@dataclass(frozen=True)
class BenchConfig:
    """Benchmark settings.

    Attributes:
        radius_m: a retrieval is correct within this distance (paper: 25 m OORD, 20 m MulRan / Boreas).
        rotation_stress: also run every query with a random heading offset (seeded) and report the drop.
        rotation_seed: seed of the heading offsets.
        rotation_limit: run the rotation stress on at most this many queries per sequence (evenly spread;
            the unrotated Recall@1 it is compared with is taken on the same queries); None = all.
        use_cache: read / write the on-disk feature cache.
        cache_root: feature cache folder (default ``cache_dir("bench", "features")``).
        progress: tqdm progress bars.
    """

    radius_m: float = 20.0
    rotation_stress: bool = True
    rotation_seed: int = 0
    rotation_limit: int | None = None
    use_cache: bool = True
    cache_root: Path | None = None
    progress: bool = True


@dataclass
class PreparedSet:
    """Prepared records of one method on one sequence (+ how long each took to compute, ms)."""

    records: list[Prepared]
    compute_ms: np.ndarray


@dataclass
class MethodRun:
    """What ``evaluate_method`` returns: the outcome arrays, the summary and timings."""

    outcome: QueryOutcome
    summary: dict[str, Any]
    search_ms: float
    extra: dict[str, Any] = field(default_factory=dict)


def sr_rule(method: PlaceRecognitionMethod) -> str:
    """Success rule of the paper: full pose -> ``pose``; heading only -> ``heading``; else ``none``."""
    if method.provides_pose:
        return "pose"
    return "heading" if method.provides_heading else "none"


def prepare_sequence(methods: Seq[PlaceRecognitionMethod], seq: Sequence, config: BenchConfig,
                     yaw_offsets: np.ndarray | None = None, variant: str = "",
                     bar: tqdm | None = None) -> dict[str, PreparedSet]:
    """Prepared records of every method for every scan of ``seq`` (cached; each scan read at most once).

    Args:
        yaw_offsets: optional (N,) heading offsets [rad]; scan i is turned by ``yaw_offsets[i]`` first
            (``rotate_scan``) and cached under ``<stem>@<variant>@yaw<offset>``.
        bar: the run's overall progress bar (advanced by one step per scan and method); without it a bar of
            its own is shown when ``config.progress``.
    """
    skey = sequence_key(seq.name, seq.root, seq.preset.name)
    caches = {m.name: FeatureCache(m.cache_key, skey, config.cache_root, config.use_cache, source_root=seq.root)
              for m in methods}
    out: dict[str, PreparedSet] = {m.name: PreparedSet([], np.zeros(len(seq))) for m in methods}
    try:
        desc = f"{seq.name}{' ' + variant if variant else ''}: features"
        if bar is not None:
            bar.set_postfix_str(desc, refresh=False)
        for i in tqdm(range(len(seq)), desc=desc, disable=not config.progress or bar is not None, leave=False):
            path = Path(seq.scan_paths[i])
            key = path.stem + (f"@{variant}" if variant else "")
            if yaw_offsets is not None:  # the offset itself is part of the key: a record is one exact input
                key += f"@yaw{float(yaw_offsets[i]):.9f}"
            scan = None
            for m in methods:
                hit = caches[m.name].get(key, path)
                if hit is None:
                    if scan is None:
                        scan = seq.load_scan(i)
                        if yaw_offsets is not None:
                            scan = rotate_scan(scan, float(yaw_offsets[i]))
                    t0 = time.perf_counter()
                    rec = m.prepare(scan)
                    ms = (time.perf_counter() - t0) * 1e3
                    caches[m.name].put(key, rec, ms, path)
                    hit = (rec, ms)
                out[m.name].records.append(hit[0])
                out[m.name].compute_ms[i] = hit[1]
            if bar is not None:
                bar.update(len(methods))
    finally:
        for c in caches.values():
            c.close()
    return out


def evaluate_method(method: PlaceRecognitionMethod, db: PreparedSet, db_poses: np.ndarray, query: PreparedSet,
                    query_poses: np.ndarray, radius_m: float, fit: bool = True,
                    progress: bool = False, label: str = "", bar: tqdm | None = None,
                    pose_refs: tuple[np.ndarray, np.ndarray] | None = None) -> MethodRun:
    """Fit (optional) on the database, then answer every query; metrics per the paper's rules.

    Args:
        db_poses: (N, 3) database poses T_map_keyframe; query_poses: (Q, 3) ground-truth T_map_query, both at
            the scan timestamps (retrieval correctness).
        bar: the run's overall progress bar (one step per query); replaces the per-method bar.
        pose_refs: (database (N, 3), query (Q, 3)) poses at the scans' mid-sweep times
            (docs/CONVENTIONS.md): a pose-estimating method localizes against the first and its poses are
            scored against the second; a heading-only method's heading is applied to the first and scored against
            the second. None: ``db_poses`` / ``query_poses``.
    """
    rule = sr_rule(method)
    # a heading, too, relates two whole sweeps, i.e. their mid-sweep poses: a heading-only method (ReFeree) scored
    # against the scan-timestamp yaw lost correct answers at corners (QA session 38: 3 of 51 on a U-turn)
    refs = pose_refs if rule in ("pose", "heading") else None
    kf_poses = refs[0] if refs is not None else db_poses
    gt_poses = refs[1] if refs is not None else None
    if fit:
        method.fit(db.records)
    index = method.build_index([method.describe_prepared(r) for r in db.records])
    if bar is not None:  # ReRadar measures its map's place repetition here (~1 min on 2,238 keyframes)
        bar.set_postfix_str(f"{label}{method.name}: preparing the database")
    method.ready_database(index, db.records, kf_poses)  # one-off per-database work stays out of the timing
    q = len(query.records)
    retrieved = np.zeros(q, np.int64)
    dist = np.zeros(q)
    est = np.full((q, 3), np.nan)
    covariance = np.full((q, 3, 3), np.nan)  # ReRadar's pose covariances (NaN: none)
    by_descriptor = np.full(q, -1, np.int64)  # global-descriptor top 1 of re-ranking methods (-1: none)
    t_total = 0.0
    if bar is not None:
        bar.set_postfix_str(f"{label}{method.name}: queries", refresh=False)
    for i in tqdm(range(q), desc=f"{label}{method.name}: queries", disable=not progress or bar is not None,
                  leave=False):
        t0 = time.perf_counter()
        q_desc = method.describe_prepared(query.records[i])
        r = method.localize(query.records[i], q_desc, index, db.records, kf_poses)
        t_total += time.perf_counter() - t0
        if bar is not None:
            bar.update(1)
        retrieved[i], dist[i] = r.index, r.distance
        if r.descriptor_index is not None:
            by_descriptor[i] = r.descriptor_index
        if r.pose is not None:
            est[i] = r.pose
            if r.pose_covariance is not None:
                covariance[i] = r.pose_covariance
        elif r.heading_rad is not None:
            # heading-only: the keyframe's position, the estimated yaw (only the yaw is scored)
            est[i] = compose(kf_poses[r.index], np.array([0.0, 0.0, r.heading_rad]))
    outcome = make_outcome(retrieved, dist, est, query_poses, db_poses, radius_m, rule, gt_poses)
    if np.isfinite(covariance).any():
        outcome.pose_covariance = covariance
    summary = summarise(outcome, query_poses, db_poses, radius_m, rule, gt_poses)
    search_ms = 1e3 * t_total / max(q, 1)
    summary["ms_per_query"] = float(np.nanmean(query.compute_ms) + search_ms) if q else None
    summary["pose_covariance"] = (covariance_calibration(outcome, query_poses if gt_poses is None else gt_poses, radius_m)
                                  if rule == "pose" else None)
    summary["recall@1_descriptor"] = descriptor_recall_at_1(by_descriptor, outcome.positive, query_poses,
                                                            db_poses, radius_m)
    return MethodRun(outcome, summary, search_ms)


def descriptor_recall_at_1(by_descriptor: np.ndarray, positive: np.ndarray, query_poses: np.ndarray,
                           db_poses: np.ndarray, radius_m: float) -> float | None:
    """Recall@1 (%, over revisit queries) of the global descriptor's own top 1, before any re-ranking.

    Args:
        by_descriptor: (Q,) int database index of each query's nearest global descriptor; -1 where the method
            does not re-rank (then the headline Recall@1 already is the descriptor's and this returns None).
        positive: (Q,) bool, the query has a database keyframe within ``radius_m``.
        query_poses: (Q, 3) T_map_query; db_poses: (N, 3) T_map_keyframe (metres, radians).
    """
    if len(by_descriptor) == 0 or np.any(by_descriptor < 0) or not np.any(positive):
        return None
    hit = retrieval_correct(query_poses, db_poses[by_descriptor, :2], radius_m)
    return float(100.0 * np.mean(hit[positive]))


def clear_per_query(folder: Path) -> list[Path]:
    """Remove the per-query arrays (``<folder>/<pair>/<method>.npz``) of an earlier run and the sub-folders
    left empty; any other file stays. Returns the removed ``.npz`` paths."""
    removed: list[Path] = []
    if not folder.is_dir():
        return removed
    for sub in sorted(p for p in folder.iterdir() if p.is_dir() and not p.is_symlink()):
        for f in sorted(sub.glob("*.npz")):
            if f.is_file() and not f.is_symlink():
                f.unlink()
                removed.append(f)
        if not any(sub.iterdir()):
            sub.rmdir()
    return removed


def _fresh_staging(out_dir: Path) -> Path:
    """An empty ``out_dir/per_query.staging`` (one a killed run left behind is removed first)."""
    staging = out_dir / PER_QUERY_STAGING_DIR
    discard_per_query_staging(out_dir)
    staging.mkdir(parents=True)
    return staging


def discard_per_query_staging(out_dir: Path) -> None:
    """Remove the per-query arrays of a run that did not complete (``out_dir/per_query.staging``); the earlier
    run's ``per_query`` stays as it was."""
    staging = Path(out_dir) / PER_QUERY_STAGING_DIR
    if staging.is_symlink() or staging.is_file():
        staging.unlink()
    elif staging.is_dir():
        shutil.rmtree(staging)


def commit_per_query(out_dir: Path) -> list[Path]:
    """Replace the earlier run's ``out_dir/per_query/*/*.npz`` with the completed run's staged arrays.

    The earlier arrays are removed (``clear_per_query``: other files there stay), each staged file is moved in
    by a rename within ``out_dir``, and the staging folder is removed. Returns the paths now in ``per_query``.

    Call it once the run has completed, right before its results.json is written: until then an interrupted or
    failed run leaves the earlier results and their per-query files together.
    """
    out_dir = Path(out_dir)
    staging, final = out_dir / PER_QUERY_STAGING_DIR, out_dir / PER_QUERY_DIR
    clear_per_query(final)
    moved: list[Path] = []
    if staging.is_dir():
        for f in sorted(staging.rglob("*.npz")):
            dest = final / f.relative_to(staging)
            dest.parent.mkdir(parents=True, exist_ok=True)
            os.replace(f, dest)
            moved.append(dest)
    discard_per_query_staging(out_dir)
    return moved


def min_database_scans(method: PlaceRecognitionMethod) -> int:
    """Fewest database scans ``method`` can be fitted on (``PlaceRecognitionMethod.min_database_scans``: 1 for
    most; ResNet18-NetVLAD 5, more descriptors than NetVLAD centres)."""
    return method.min_database_scans()


def check_database_sizes(pairs: Seq[BenchPair], methods: Seq[PlaceRecognitionMethod]) -> None:
    """Refuse, before any scan is read, a database too small for one of ``methods`` (``min_database_scans``).

    Raises:
        ConfigError: naming the method, the scans it needs and has, and how to go on without it.
    """
    for pair in pairs:
        n = len(pair.database)
        for m in methods:
            need = min_database_scans(m)
            if n < need:
                raise ConfigError(
                    f"{m.name} needs a database of at least {need} scans (it fits its vocabulary on the database), "
                    f"but database {pair.database.name!r} of {pair.name!r} has {n}; give a longer database (a "
                    f"smaller --every, a larger --limit or a later --split-at) or drop {m.name} from --methods")


def _save_outcome(path: Path, run: MethodRun, query_xy: np.ndarray, db_xy: np.ndarray,
                  query_pose_mid_sweep: np.ndarray) -> None:
    """``per_query/<sequence>/<method>.npz`` (docs/BENCHMARKS.md, "Per-query files"): two instants, each named -
    ``query_xy`` / ``db_xy`` are the scans' positions at their timestamps (first azimuth, what the datasets' pose
    files give and what retrieval is judged on), ``est_pose`` and ``query_pose_mid_sweep`` are mid-sweep poses (x m,
    y m, yaw rad; what the errors are measured against), and ReRadar's ``pose_covariance`` (Q, 3, 3) of ``est_pose`` (x m,
    y m, yaw rad; NaN rows: none)."""
    o = run.outcome
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, retrieved=o.retrieved, distance=o.distance, est_pose=o.est_pose,
                        correct=o.correct, positive=o.positive, heading_err_deg=o.heading_err_deg,
                        trans_err_m=o.trans_err_m, query_xy=query_xy, db_xy=db_xy,
                        query_pose_mid_sweep=query_pose_mid_sweep,
                        **({} if o.pose_covariance is None else {"pose_covariance": o.pose_covariance}))


def _rotation_indices(n: int, limit: int | None) -> np.ndarray:
    """The queries of the rotation stress test: all, or ``limit`` evenly spread."""
    if limit is not None and 0 < limit < n:
        return np.linspace(0, n - 1, limit).round().astype(np.int64)
    return np.arange(n)


def _rotation_stress(pair: BenchPair, methods: Seq[PlaceRecognitionMethod], dbp: dict[str, PreparedSet],
                     qp: dict[str, PreparedSet], config: BenchConfig, mid: tuple[np.ndarray, np.ndarray],
                     bar: tqdm | None = None) -> dict[str, Any]:
    """Recall@1 (over revisit queries) of the same queries with and without a random heading offset.

    ``mid``: the pair's (database, query) mid-sweep poses (``evaluate_method``'s ``pose_refs``)."""
    n = len(pair.query)
    idx = _rotation_indices(n, config.rotation_limit)
    query = pair.query.subset(idx)
    yaw = heading_offsets(n, config.rotation_seed, pair.query.preset.num_azimuths)[idx]
    rq = prepare_sequence(methods, query, config, yaw_offsets=yaw, variant=f"rot{config.rotation_seed}", bar=bar)
    q_poses = query.poses.poses
    rq_poses = rotate_pose(q_poses, yaw)
    db_poses = pair.database.poses.poses
    db_mid, q_mid = mid[0], mid[1][idx]
    stress: dict[str, Any] = {}
    for m in methods:
        base_set = PreparedSet([qp[m.name].records[i] for i in idx], qp[m.name].compute_ms[idx])
        base = evaluate_method(m, dbp[m.name], db_poses, base_set, q_poses, config.radius_m, fit=False,
                               label=f"{pair.name} unrotated ", bar=bar, pose_refs=(db_mid, q_mid)).summary
        run = evaluate_method(m, dbp[m.name], db_poses, rq[m.name], rq_poses, config.radius_m, fit=False,
                              progress=config.progress, label=f"{pair.name} rotated ", bar=bar,
                              pose_refs=(db_mid, rotate_pose(q_mid, yaw))).summary
        drop = None if base["recall@1"] is None or run["recall@1"] is None else base["recall@1"] - run["recall@1"]
        stress[m.name] = {"n_queries": int(len(idx)), "n_revisit": base["n_revisit"], "recall@1": base["recall@1"],
                          "recall@1_rotated": run["recall@1"], "drop": drop,
                          "sr": base["sr"], "sr_rotated": run["sr"]}
    return stress


def _database_key(pair: BenchPair) -> str:
    return sequence_key(pair.database.name, pair.database.root, pair.database.preset.name) + f"-{len(pair.database)}"


def total_steps(pairs: Seq[BenchPair], n_methods: int, config: BenchConfig) -> int:
    """Steps of ``run_benchmark``'s overall progress bar: one per (scan, method) feature record (each database
    once) and one per (query, method) answer, rotation stress included."""
    steps, seen = 0, set()
    for pair in pairs:
        dkey = _database_key(pair)
        if dkey not in seen:
            seen.add(dkey)
            steps += len(pair.database) * n_methods
        steps += 2 * len(pair.query) * n_methods  # features + answers
        if config.rotation_stress:
            steps += 3 * len(_rotation_indices(len(pair.query), config.rotation_limit)) * n_methods
    return steps


def run_benchmark(pairs: Seq[BenchPair], methods: Seq[PlaceRecognitionMethod], out_dir: Path,
                  config: BenchConfig = BenchConfig(), suite: str | None = None,
                  commit: bool = True) -> dict[str, Any]:
    """Run every method on every pair; write per-query arrays under ``out_dir/per_query`` and return the
    results dict (``{"suite", "settings", "sequences": {SEQ: {METHOD: metrics}}, "rotation_stress"}``).

    With ``config.progress`` one overall tqdm bar (steps of ``total_steps``, with ETA) covers every method
    and sequence; its postfix names the current stage.

    The arrays are written to ``out_dir/per_query.staging`` first and replace the ``.npz`` files an earlier run
    left under ``out_dir/per_query`` only when every pair has run (``commit_per_query``), so the folder then
    holds this run's arrays only (nothing else in ``out_dir`` is touched). A failed or interrupted run removes
    its staging folder and leaves the earlier arrays. ``commit=False``: the caller commits (after the work it
    still has to do, right before it writes results.json) or discards (``discard_per_query_staging``).

    Raises:
        ConfigError: two pairs or two methods of one name (their results would overwrite each other); a
            database too small for a method (``check_database_sizes``). Both before anything is computed."""
    out_dir = Path(out_dir)
    for what, names in (("pair", [p.name for p in pairs]), ("method", [m.name for m in methods])):
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ConfigError(f"two {what}s are named {twice[0]!r}: each needs its own name in the results")
    check_database_sizes(pairs, methods)
    staging = _fresh_staging(out_dir)
    try:
        results = _run_pairs(pairs, methods, staging, config, suite)
        if commit:
            commit_per_query(out_dir)
    except BaseException:  # failed or interrupted (Ctrl-C): the earlier run's arrays stay
        discard_per_query_staging(out_dir)
        raise
    return results


def _run_pairs(pairs: Seq[BenchPair], methods: Seq[PlaceRecognitionMethod], per_query: Path,
               config: BenchConfig, suite: str | None) -> dict[str, Any]:
    """``run_benchmark``'s work: every method on every pair, per-query arrays written under ``per_query``."""
    results: dict[str, Any] = {
        "suite": suite,
        "settings": {"radius_m": config.radius_m, "rotation_seed": config.rotation_seed,
                     "methods": [m.name for m in methods],
                     "method_params": {m.name: m.params() for m in methods},
                     "pairs": {p.name: {"database": p.database.name, "query": p.query.name,
                                        "query_folder": str(Path(p.query.root).resolve()),
                                        "n_database": len(p.database), "n_query": len(p.query),
                                        "split": p.split}
                               for p in pairs},
                     # the reference machine is shared: timings are only comparable at similar load
                     "load_average_1min_at_start": os.getloadavg()[0], "cpu_count": os.cpu_count()},
        "sequences": {},
        "rotation_stress": {} if config.rotation_stress else None,
        "rotation_stress_settings": {"seed": config.rotation_seed, "limit": config.rotation_limit,
                                     "offsets": "uniform [0, 360) deg, whole azimuth steps"},
    }
    db_cache: dict[str, dict[str, PreparedSet]] = {}
    fitted_on: dict[str, str] = {}
    bar = tqdm(total=total_steps(pairs, len(methods), config), desc="bench", unit="step", dynamic_ncols=True,
               disable=not config.progress)
    try:
        for pair in pairs:
            dkey = _database_key(pair)
            if dkey not in db_cache:
                db_cache[dkey] = prepare_sequence(methods, pair.database, config, bar=bar)
            dbp = db_cache[dkey]
            qp = prepare_sequence(methods, pair.query, config, bar=bar)
            db_poses = pair.database.poses.poses
            q_poses = pair.query.poses.poses
            mid = (pair.database.mid_sweep_poses(), pair.query.mid_sweep_poses())
            seq_res: dict[str, Any] = {}
            for m in methods:
                need_fit = fitted_on.get(m.name) != dkey
                run = evaluate_method(m, dbp[m.name], db_poses, qp[m.name], q_poses, config.radius_m,
                                      fit=need_fit, label=f"{pair.name} ", bar=bar, pose_refs=mid)
                fitted_on[m.name] = dkey
                seq_res[m.name] = run.summary
                _save_outcome(per_query / pair.name / f"{m.name}.npz", run, q_poses[:, :2], db_poses[:, :2],
                              mid[1])
                r1 = run.summary["recall@1"]
                logger.info("%s %s: %s", pair.name, m.name, "no revisit queries (Recall@1 not applicable)"
                            if r1 is None else f"Recall@1 {r1:.2f}% (revisit queries)")
            results["sequences"][pair.name] = seq_res
            if config.rotation_stress:
                results["rotation_stress"][pair.name] = _rotation_stress(pair, methods, dbp, qp, config, mid, bar)
    finally:
        bar.close()
    results["settings"]["load_average_1min_at_end"] = os.getloadavg()[0]
    return results
