"""``reradar bench``: every method on the same database / query sequences -> results.json, results.md, plots.

Ways to name the data:
  reradar bench --suite boreas-sim --out DIR                       (simulated suites, rendered and cached)
  reradar bench --database DIR --query DIR [--query DIR ...] --preset boreas [--radius 20] --out DIR
                                                                  (real recordings in their own layouts)
  reradar bench --database DIR --split-at 765 --preset mulran --out DIR
                                                                  (single session: scans before the split are
                                                                   the database, the rest the queries)
  reradar bench --suite loop-sim --split-at 120s [--split-sequence laps2-3] --out DIR
"""

from __future__ import annotations

import fcntl
import json
import logging
import math
import os
from pathlib import Path
from typing import IO

import numpy as np
import typer

from reradar_core.errors import ReRadarError

__all__ = ["register", "bench"]

logger = logging.getLogger(__name__)


def _split(values: list[str] | None) -> list[str]:
    out: list[str] = []
    for v in values or []:
        out += [s.strip() for s in v.split(",") if s.strip()]
    return out


def _safe(text: str) -> str:
    """``text`` as a folder-name part (the default output folder names the split)."""
    return "".join(c if c.isalnum() else "_" for c in text.strip())


def _positive(value: float | None) -> float | None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise typer.BadParameter(f"must be a positive number of metres, got {value}")
    return value


def _non_negative(value: int) -> int:
    if value < 0:  # numpy's generators take seeds >= 0: refused here, not after every feature is computed
        raise typer.BadParameter(f"must be 0 or more, got {value}")
    return value


def bench(
    suite: str | None = typer.Option(None, "--suite", help="Simulated suite: smoke, boreas-sim, loop-sim, "
                                     "loop-sim-hard, offroad-sim, offroad-sim-hard (rendered on first use, cached)."),
    database: Path | None = typer.Option(None, "--database", help="Reference (map) sequence folder."),
    query: list[Path] | None = typer.Option(None, "--query", help="Query sequence folder (repeatable; each "
                                         "folder once; folders of one name are reported as PARENT-NAME)."),
    preset: str | None = typer.Option(None, "--preset", help="Radar preset of the folders: boreas, "
                                      "boreas-2021, oxford, oord, mulran (not with --suite: a suite has its own)."),
    layout: str | None = typer.Option(None, "--layout", help="Dataset layout (boreas/oxford/mulran); "
                                      "detected when omitted."),
    methods: list[str] | None = typer.Option(None, "--methods", "-m", help="Comma-separated methods "
                                             "(default: all baselines and every shipped ReRadar model; a method "
                                             "named twice runs once). A ReRadar model name with '+far' (e.g. "
                                             "our-3-offroad-w05+far) adds the far view for refused answers, "
                                             "'+dense' the far view and its dense registration for open-land "
                                             "answers both views refuse (ours, docs/MODEL.md)."),
    out: Path | None = typer.Option(None, "--out", help="Output folder (default: cache/bench/<suite>). "
                               "When the run completes, its per_query/*/*.npz replace an earlier run's there; "
                               "a run that fails or is interrupted leaves them; other files stay."),
    radius: float | None = typer.Option(None, "--radius", callback=_positive, help="Correct-retrieval radius, metres (default: "
                                        "the suite's, or 25 OORD/Oxford, 20 MulRan/Boreas)."),
    every: int | None = typer.Option(None, "--every", min=1, help="Use every N-th scan (default 1: every scan of a "
                                     "folder; suites are rendered at their protocol spacing and keep it)."),
    split_at: str | None = typer.Option(None, "--split-at", help="Single-session split of one sequence: "
                                        "database = scans before, queries = scans from the split on. A scan "
                                        "index (765, 0-based, before --every), seconds after the first scan "
                                        "(120s) or a scan timestamp in µs (t=1566535872045000). With --database "
                                        "(no --query) or --suite."),
    time_unit: str | None = typer.Option(None, "--time-unit", help="Unit of the folders' pose-file timestamps "
                                         "(s, ms, us, ns) when they are not absolute UTC times; never guessed."),
    split_sequence: str | None = typer.Option(None, "--split-sequence", help="Suite sequence to split with "
                                              "--split-at (default: the suite's database sequence)."),
    limit: int | None = typer.Option(None, "--limit", min=1, help="At most this many scans per sequence after "
                                     "subsampling (evenly spread over the sequence, not the first N; "
                                     "--query-limit, when given, replaces it for the query sequences)."),
    query_limit: int | None = typer.Option(None, "--query-limit", min=1, help="At most this many queries per query "
                                           "sequence (evenly spread; the database keeps its frames)."),
    rotation: bool = typer.Option(True, "--rotation/--no-rotation", help="Run the rotation stress test."),
    rotation_limit: int | None = typer.Option(None, "--rotation-limit", min=1, help="Rotation stress on at most "
                                              "this many queries per sequence (evenly spread)."),
    timing: bool = typer.Option(True, "--timing/--no-timing", help="Measure ReRadar's stage timings."),
    timing_scans: int = typer.Option(20, "--timing-scans", min=1, help="Query scans for the stage timings."),
    yaw_curve: bool = typer.Option(True, "--yaw-curve/--no-yaw-curve", help="Yaw-consistency curve of F'."),
    plots: bool = typer.Option(True, "--plots/--no-plots", help="Write PNG figures."),
    cache: bool = typer.Option(True, "--cache/--no-cache", help="Use the on-disk feature cache."),
    threads: int = typer.Option(1, "--threads", min=1, help="Torch / BLAS threads (the machine is shared)."),
    seed: int = typer.Option(0, "--seed", callback=_non_negative, help="Seed of the rotation-stress heading offsets "
                             "(0 or more)."),
) -> None:
    """Benchmark ReRadar against RingKey, RaPlace, RadVLAD, ResNet18-NetVLAD and ReFeree."""
    import torch

    from reradar_core.baselines import default_method_names, make_method
    from reradar_core.benchmark.extras import add_timing, add_yaw_consistency
    from reradar_core.benchmark.plots import make_all_plots
    from reradar_core.benchmark.results import results_markdown, write_results
    from reradar_core.benchmark.runner import (
        BenchConfig,
        commit_per_query,
        discard_per_query_staging,
        run_benchmark,
    )
    from reradar_core.benchmark.suites import pairs_from_folders, pairs_from_suite, suite_spacing
    from reradar_core.paths import cache_dir, output_dir
    from reradar_core.threads import limit_blas_threads

    torch.set_num_threads(max(1, threads))
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):  # BLAS libraries loaded later (scipy's) read these
        os.environ.setdefault(var, str(max(1, threads)))
    staged: Path | None = None  # --out while this run's per-query arrays wait in its staging folder
    lock: IO[str] | None = None  # held on --out while this run writes there
    try:
        if (suite is None) == (database is None):
            raise typer.BadParameter("give either --suite NAME or --database DIR with --query DIR")
        if methods is not None and not _split(methods):  # `-m "$M"` with M unset: not "every method" silently
            raise typer.BadParameter("--methods names no method; give e.g. -m ringkey,raplace,our-3-boreas-w05, or "
                                     "leave it out for every baseline and shipped model")
        if out is not None:  # a file in the way is found now, not after the benchmark ran
            output_dir(out, "--out", create=False)
            for opt, folder in [("--database", database)] + [("--query", q) for q in query or []]:
                if folder is not None and out.resolve().is_relative_to(folder.resolve()):
                    # results.json, plots and per_query/ would land among the scans (and be read with them later)
                    raise typer.BadParameter(f"--out {out} is inside the {opt} folder {folder}: the results would be "
                                             "written among its scans; choose a folder outside the scan folders")
        if database is not None and split_at is None and any(q.resolve() == database.resolve() for q in query or []):
            raise typer.BadParameter("a --query folder is the --database folder: every query would find itself "
                                     "(Recall@1 100 %); give another drive, or --split-at to split one drive")
        # the methods first: an unknown name is refused before a suite is rendered (QA session 38)
        names, dropped = unique_methods(_split(methods) or default_method_names())
        if dropped:
            typer.echo(f"note: --methods names {', '.join(dropped)} more than once; each runs once")
        method_objs, aliases = unique_method_objects([make_method(n) for n in names], labels=names)
        if aliases:  # e.g. 'ours' and the default model, 'netvlad' and 'resnet18-netvlad'
            typer.echo("note: --methods names one method twice: " + ", ".join(f"{a} is {k}" for a, k in aliases)
                       + " (an alias); it runs once")
            names = [m.name for m in method_objs]
        if suite is not None:
            if query or time_unit:
                given = " and ".join(o for o, v in (("--query", query), ("--time-unit", time_unit)) if v)
                raise typer.BadParameter(f"{given} {'are' if ' and ' in given else 'is'} for folders; a suite names its "
                                         "own sequences and their times")
            if preset is not None:
                raise typer.BadParameter("--preset is for folders; a suite is rendered with its own radar preset "
                                         "(drop --preset, or render with `reradar sim --preset` and bench the "
                                         "folders)")
            pairs, default_radius = pairs_from_suite(suite, every=every, limit=limit, query_limit=query_limit,
                                                     split_at=split_at, split_sequence=split_sequence)
            label = suite if split_at is None else f"{suite}-{split_sequence or 'database'}-split-{_safe(split_at)}"
            spacing = suite_spacing(suite)
            rendered = ", ".join(f"{k} every {v}" for k, v in spacing.items())
            every_note = (f"suite protocol spacing (rendered: {rendered})" if every is None else
                          f"{_every_text(every)} of the suite's renders ({rendered})")
        else:
            assert database is not None
            if split_sequence is not None:
                raise typer.BadParameter("--split-sequence is for suites; a folder is split as a whole")
            pairs, default_radius = pairs_from_folders(database, list(query or []), preset=preset, layout=layout,
                                                       every=every or 1, limit=limit, query_limit=query_limit,
                                                       split_at=split_at, time_unit=time_unit)
            if split_at is None:
                for p in pairs:  # a copy (or hard link) of the database passes the path check above
                    if _same_scans(p.database, p.query):
                        raise typer.BadParameter(f"query sequence {p.query.name!r} holds the database's scans (same "
                                                 "names, sizes and times: a copy of it): every query would find "
                                                 "itself (Recall@1 100 %); give another drive, or --split-at to "
                                                 "split one drive")
            label = f"{database.name}" + ("" if split_at is None else f"-split-{_safe(split_at)}")
            every_note = (f"every {every or 1} scan(s) of the folders"
                          + (" (default 1: pass --every N to subsample)" if every is None else ""))
        if limit is not None or query_limit is not None:  # said where the spacing is (QA session 38: results.md
            # read "every 1 scan" for a run that kept 10 of 40 database scans)
            kept = [f"at most {limit} scans per sequence" if limit is not None else "",
                    f"at most {query_limit} queries per query sequence" if query_limit is not None else ""]
            every_note += "; then " + " and ".join(k for k in kept if k) + " (evenly spread: --limit / --query-limit)"
        # every BLAS loaded by now (numpy's, scipy's, opencv's) gets --threads: two pools fighting over 2 cores
        # make the screen's descriptor product 20x slower (docs/BENCHMARKS.md, issue 12)
        limit_blas_threads(max(1, threads))
        out_dir = out or cache_dir("bench", label)
        cfg = BenchConfig(radius_m=radius or default_radius, rotation_stress=rotation, rotation_seed=seed,
                          rotation_limit=rotation_limit,
                          use_cache=cache)
        typer.echo(f"bench {label}: {len(pairs)} query sequence(s), methods {names}, radius {cfg.radius_m} m")
        typer.echo(f"frame spacing: {every_note}")
        for p in pairs:
            cut = (f" (split of {p.split['sequence']} at scan {p.split['index']} of {p.split['n_scans']})"
                   if p.split else "")
            typer.echo(f"  {p.name}: database sequence {p.database.name!r} ({len(p.database)} scans), query "
                       f"sequence {p.query.name!r} ({len(p.query)} scans){cut}")
        lock = _lock_out(out_dir)
        staged = out_dir
        results = run_benchmark(pairs, method_objs, out_dir, cfg, suite=label, commit=False)
        results["settings"].update(threads=threads, every=every if every is not None else (1 if suite is None
                                                                                            else "suite"),
                                   every_note=every_note, limit=limit, query_limit=query_limit, split_at=split_at,
                                   # where each learned method's network ran (ONNX Runtime or torch): its timings
                                   # depend on it (reradar_core.model.runtime)
                                   network_runtime={m.name: str(getattr(getattr(m, "extractor", None), "runtime", "torch"))
                                                    for m in method_objs if getattr(m, "extractor", None) is not None},
                                   # the registry model each ReRadar method ran ('ours' = the default model)
                                   method_models={m.name: str(getattr(m.extractor, "name", "") or "")  # type: ignore[attr-defined]
                                                  for m in method_objs if getattr(m, "extractor", None) is not None},
                                   # a run on recorded folders names the database folder, not a suite
                                   database_folder=None if database is None else str(database.resolve()))
        ours = [m for m in method_objs if m.provides_pose]
        # after the progress bar: each stage says what it does, so a run that seems done is not read as hung
        if timing and ours:
            typer.echo(f"stage timings: {_primary(ours).name} on {min(timing_scans, len(pairs[0].query))} query "
                       f"scans of {pairs[0].name} ...")
            add_timing(results, _primary(ours), pairs[0], cfg, timing_scans, threads)
        if yaw_curve and ours and plots:
            typer.echo(f"yaw-consistency curve of F' ({', '.join(m.name for m in ours)}) ...")
            add_yaw_consistency(results, ours, pairs[0], out_dir)
        # the run is complete: its per-query arrays replace the earlier run's, then its results are written
        commit_per_query(out_dir)
        staged = None
        earlier_figures = _figures_of(out_dir / "results.json")  # an earlier run's, read before it is replaced
        jpath, mpath = write_results(results, out_dir)
        if plots:
            typer.echo("figures ...")
        figs = make_all_plots(results, out_dir) if plots else []
        # rewrite with the figure list (results.json is the single source for the docs)
        results["figures"] = [str(p.name) for p in figs] + results.get("figures", [])
        jpath.write_text(json.dumps(results, indent=2) + "\n")
        _remove_stale_figures(out_dir, earlier_figures, results["figures"])
    except ReRadarError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    finally:
        if staged is not None:  # failed or interrupted after the benchmark ran: the earlier arrays stay
            discard_per_query_staging(staged)
        if lock is not None:
            lock.close()  # releases the --out lock
    typer.echo(results_markdown(results))
    n_figs = len(results.get("figures", []))  # the yaw-consistency curve included
    typer.echo(f"wrote {jpath}, {mpath}" + (f" and {n_figs} figure{'' if n_figs == 1 else 's'}" if n_figs else ""))


def _same_scans(database, query) -> bool:
    """True when two sequences hold the same scans: the same file names, sizes and scan times."""
    if len(database) != len(query) or not np.array_equal(database.timestamps_us, query.timestamps_us):
        return False
    return all(a.name == b.name and a.stat().st_size == b.stat().st_size
               for a, b in zip(database.scan_paths, query.scan_paths, strict=True))


#: The lock file a run holds in its --out folder while it writes there.
OUT_LOCK_FILE = ".reradar-bench.lock"


def _lock_out(out_dir: Path) -> IO[str]:
    """Take ``out_dir``'s run lock (created with the folder), or refuse: two runs on one --out deleted each other's
    per-query arrays and left a results.json without them (QA session 38). The lock goes with the process."""
    out_dir.mkdir(parents=True, exist_ok=True)
    fh = (out_dir / OUT_LOCK_FILE).open("w")
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        fh.close()
        raise typer.BadParameter(f"--out {out_dir}: another reradar bench run is writing there; wait for it to "
                                 "finish, or choose another --out") from None
    return fh


def _figures_of(results_json: Path) -> list[str]:
    """The figure file names an earlier run's results.json lists ([] without a readable one)."""
    try:
        figures = json.loads(results_json.read_text()).get("figures", [])
    except (OSError, ValueError, AttributeError):
        return []
    return [f for f in figures if isinstance(f, str)]


def _remove_stale_figures(out_dir: Path, earlier: list[str], now: list[str]) -> None:
    """Remove the figures of the earlier run in ``out_dir`` that this run did not draw again: they showed that run's
    queries and methods beside this run's results (QA session 38). Plain ``.png`` names inside the folder only."""
    for name in set(earlier) - set(now):
        path = out_dir / name
        if Path(name).name == name and name.endswith(".png") and path.is_file() and not path.is_symlink():
            path.unlink()


def _every_text(every: int) -> str:
    """``every 2nd scan``, ``every 3rd scan``, ``every 11th scan``, ``every scan``: English ordinals."""
    if every == 1:
        return "every scan"
    suffix = "th" if 10 <= every % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(every % 10, "th")
    return f"every {every}{suffix} scan"


def unique_methods(names: list[str]) -> tuple[list[str], list[str]]:
    """``names`` without repeats (case and spaces ignored), first occurrence kept in order, and the names dropped."""
    kept: list[str] = []
    dropped: list[str] = []
    seen: set[str] = set()
    for n in names:
        key = n.strip().lower()
        if key in seen:
            dropped.append(n)
        else:
            seen.add(key)
            kept.append(n)
    return kept, dropped


def method_identity(method: object) -> tuple[str, str]:
    """What makes two method objects the same method: their class and parameters (``params()``: for ReRadar the
    weights' sha256), not their names (``ours`` is the default model under another name)."""
    params: dict = getattr(method, "params", dict)()
    cls = type(method)
    return f"{cls.__module__}.{cls.__qualname__}", json.dumps(params, sort_keys=True, default=str)


def unique_method_objects(methods: list, labels: list[str] | None = None) -> tuple[list, list[tuple[str, str]]]:
    """``methods`` without a second object of the same method (``method_identity``), the first kept in order,
    and for each dropped one (the name it was given as, ``labels[i]`` or its own name; the kept one's, likewise)."""
    kept: list = []
    first: dict[tuple[str, str], str] = {}
    dropped: list[tuple[str, str]] = []
    for i, m in enumerate(methods):
        given = labels[i] if labels is not None else m.name
        key = method_identity(m)
        if key in first:
            dropped.append((given, first[key]))
        else:
            first[key] = given
            kept.append(m)
    return kept, dropped


def _primary(ours: list) -> object:
    """The ReRadar setting the timing table describes: the default model, else a target-adapted one."""
    try:
        from reradar_core.model import DEFAULT_MODEL
    except ImportError:  # pragma: no cover
        DEFAULT_MODEL = ""
    for test in (lambda n: n in ("ours", DEFAULT_MODEL), lambda n: n.startswith("our-3") and "resnet" not in n):
        for m in ours:
            if test(m.name):
                return m
    return ours[0]


def register(app: typer.Typer) -> None:
    """Add ``reradar bench`` to the CLI."""
    app.command("bench")(bench)
