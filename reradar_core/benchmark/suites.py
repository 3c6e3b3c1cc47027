"""Which sequences a benchmark compares: a simulated suite (``reradar_core.sim.suites``) or real folders.

Single-session protocol (the paper's MulRan protocol: DCC01 split at scan 765, KAIST03 at 1420): one sequence
is cut in two; the database is every scan *before* the split, the queries are the scans from the split on.
The split is given as text (``parse_split``):

- ``765``: scan index, 0-based, in time order, counted over the whole sequence *before* ``--every``
  subsampling (the paper's scan number): scans 0..764 form the database, 765.. the queries;
- ``120s`` (or ``120.5s``): seconds after the sequence's first scan (database: scans earlier than that);
- ``t=1566535872045000``: an absolute scan timestamp in microseconds (Boreas / Oxford file names; MulRan
  file names are nanoseconds, divide by 1000). The split is at the first scan at or after it.

Each part is then subsampled with ``every`` and capped with ``limit`` / ``query_limit`` on its own.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from reradar_core.benchmark.runner import BenchPair
from reradar_core.errors import ConfigError, DatasetError
from reradar_core.io.datasets import (
    SIM_META_FILE,
    Sequence,
    detect_layout,
    layout_presets_ambiguous,
    load_sequence,
    range_grid_difference,
    read_sequence_meta,
)
from reradar_core.io.presets import RadarPreset, get_preset
from reradar_core.paths import distinct_folder_labels

__all__ = ["subsample", "pairs_from_folders", "query_pair_names", "pairs_from_suite", "default_radius", "SplitSpec", "parse_split",
           "split_index", "split_pair", "per_run_odometry", "check_shared_map_frame", "check_scan_files"]


@dataclass(frozen=True)
class SplitSpec:
    """Where a single-session split falls (see the module docstring).

    Attributes:
        kind: ``index`` (scan index), ``seconds`` (after the first scan) or ``timestamp`` (absolute, µs).
        value: the number.
        text: what the user wrote.
    """

    kind: str
    value: float
    text: str


_SPLIT_HELP = "use a scan index (765), seconds after the first scan (120s) or a timestamp in µs (t=1566535872045000)"


def parse_split(text: str) -> SplitSpec:
    """``765`` -> index, ``120s`` -> seconds, ``t=<µs>`` -> timestamp.

    Raises:
        ConfigError: anything else (the message lists the accepted forms).
    """
    t = str(text).strip().lower()
    try:
        if t.startswith("t="):
            return SplitSpec("timestamp", float(int(t[2:])), text)
        if t.endswith("s") and not t.endswith("us"):
            v = float(t[:-1])
            if not np.isfinite(v) or v < 0:
                raise ValueError
            return SplitSpec("seconds", v, text)
        v = int(t)
    except ValueError:
        raise ConfigError(f"--split-at {text!r} is not understood; {_SPLIT_HELP}") from None
    if v < 0:
        raise ConfigError(f"--split-at {text!r}: a scan index must be >= 0")
    return SplitSpec("index", float(v), text)


def split_index(seq: Sequence, spec: SplitSpec) -> int:
    """Index of the first query scan of ``seq`` (scans before it form the database).

    Raises:
        ConfigError: the split leaves the database or the queries empty.
    """
    n = len(seq)
    if spec.kind == "index":
        k = int(spec.value)
    elif spec.kind == "seconds":
        t0 = int(seq.timestamps_us[0])
        k = int(np.searchsorted(seq.timestamps_us, t0 + int(round(spec.value * 1e6)), side="left"))
    else:
        k = int(np.searchsorted(seq.timestamps_us, int(spec.value), side="left"))
    if not 0 < k < n:
        span = (int(seq.timestamps_us[-1]) - int(seq.timestamps_us[0])) / 1e6
        raise ConfigError(f"--split-at {spec.text!r} falls at scan {k} of {seq.name!r}, which has {n} scans "
                          f"({span:.1f} s, timestamps {int(seq.timestamps_us[0])}..{int(seq.timestamps_us[-1])} µs): "
                          "the database (scans before) and the queries (scans from it on) must both be non-empty")
    return k


def split_pair(seq: Sequence, spec: SplitSpec, every: int = 1, limit: int | None = None,
               query_limit: int | None = None) -> BenchPair:
    """The single-session pair of ``seq``: database = scans before the split, queries = scans from it on,
    each subsampled with ``every`` and capped; ``pair.split`` describes the split for results.json.

    Both halves keep the sequence's name and folder, so they share its feature cache."""
    k = split_index(seq, spec)
    n = len(seq)
    db = subsample(seq.subset(np.arange(0, k)), every, limit)
    q = subsample(seq.subset(np.arange(k, n)), every, query_limit or limit)
    info = {"sequence": seq.name, "spec": spec.text, "kind": spec.kind, "index": k,
            "timestamp_us": int(seq.timestamps_us[k]), "n_scans": n,
            "rule": "database = scans [0, index), queries = scans [index, n), before subsampling"}
    return BenchPair(f"{seq.name}@{k}", db, q, split=info)


def subsample(seq: Sequence, every: int = 1, limit: int | None = None) -> Sequence:
    """Every ``every``-th scan (OORD protocol: every 5th frame), at most ``limit`` of them (evenly spread)."""
    if every < 1:
        raise ConfigError(f"--every must be >= 1, got {every}")
    idx = np.arange(0, len(seq), every)
    if limit is not None and limit > 0 and len(idx) > limit:
        idx = idx[np.linspace(0, len(idx) - 1, limit).round().astype(np.int64)]
    return seq.subset(idx)


def default_radius(preset_name: str) -> float:
    """The paper's radius for a preset: 25 m OORD / Oxford, 20 m MulRan / Boreas."""
    from reradar_core.evaluation import radius_for

    return float(radius_for(preset_name))


def pairs_from_folders(database: Path, queries: list[Path], preset: str | None = None, layout: str | None = None,
                       every: int = 1, limit: int | None = None, query_limit: int | None = None,
                       split_at: str | None = None, time_unit: str | None = None) -> tuple[list[BenchPair], float]:
    """Real recordings: one database folder and query folders in their dataset layouts, or, with
    ``split_at``, one folder split into database and queries (single-session protocol).

    ``limit`` caps every sequence, ``query_limit`` only the query sequences (evenly spread); ``time_unit`` is
    the pose files' timestamp unit where it cannot be told (``load_sequence``). Returns the pairs and the
    preset's radius."""
    full = load_sequence(database, layout, preset, time_unit)
    check_scan_files(full)
    if split_at is not None:
        if queries:
            raise ConfigError("--split-at takes database and queries from one sequence: give --database DIR "
                              "without --query")
        return [split_pair(full, parse_split(split_at), every, limit, query_limit)], default_radius(full.preset.name)
    if not queries:
        raise ConfigError("--database needs at least one --query DIR (or --split-at for a single-session split)")
    db = subsample(full, every, limit)
    names = query_pair_names(database, queries)
    pairs = []
    for q, name in zip(queries, names, strict=True):
        if preset is None:
            _check_recorded_presets_agree(database, db.preset, q)
            _check_query_names_its_radar(db.preset, q, layout)
        q_full = load_sequence(q, layout, preset or db.preset.name, time_unit)
        check_scan_files(q_full)
        check_shared_map_frame(full, q_full)
        pairs.append(BenchPair(name, db, subsample(q_full, every, query_limit or limit)))
    return pairs, default_radius(db.preset.name)


def per_run_odometry(seq: Sequence) -> Path | None:
    """The per-run odometry file ``seq``'s poses were integrated from, or None when they are in a map frame.

    An Oxford-layout folder (Oxford RobotCar radar, OORD) takes its poses from ``gt/radar_odometry.csv`` (or
    ``radar_odometry.csv``), integrated from the identity at the run's first scan (``io.datasets``): two runs
    share no frame. Only a render of ``reradar sim`` records where that origin lies in its world
    (``oxford_T_world_origin`` in ``reradar_sim.json``). Boreas ``applanix/radar_poses.csv`` and MulRan
    ``global_pose.csv`` hold map-frame poses.
    """
    if seq.layout != "oxford" or "oxford_T_world_origin" in read_sequence_meta(seq.root):
        return None
    for cand in (seq.root / "gt" / "radar_odometry.csv", seq.root / "radar_odometry.csv"):
        if cand.is_file():
            return cand
    return seq.root / "gt" / "radar_odometry.csv"


def check_shared_map_frame(database: Sequence, query: Sequence) -> None:
    """Refuse a database and a query run of which either has per-run odometry poses (``per_run_odometry``).

    Each such run starts at the identity, so both would be placed at one origin whatever their true places:
    revisits, Recall@1, SR and the rejection figures would all be wrong. A single run split with ``--split-at``
    is one frame and is not checked here.

    Raises:
        ConfigError: naming the run and what to do (``--split-at``, or map-frame poses in
            ``applanix/radar_poses.csv``).
    """
    for seq in (database, query):
        odo = per_run_odometry(seq)
        if odo is not None:
            raise ConfigError(
                f"{seq.root}: its poses come from {odo.relative_to(seq.root).as_posix()}, odometry that starts at "
                "the identity in every run, so the database and query runs would be placed at the same origin and "
                "every metric would be wrong; bench one run with --split-at, or give each run its poses in one map "
                "frame as applanix/radar_poses.csv beside radar/ (Boreas columns: GPSTime, easting, northing, "
                f"heading; the folder is then read in the Boreas layout: pass --preset {seq.preset.name})")


def check_scan_files(seq: Sequence) -> None:
    """Refuse a sequence whose scan list holds a folder (a directory named like ``2500000.png``) before any scan
    is read.

    Raises:
        DatasetError: naming the folder.
    """
    for path in seq.scan_paths:
        if Path(path).is_dir():
            raise DatasetError(f"{path}: is a folder, not a scan file; move it out of {Path(path).parent}")


def _check_recorded_presets_agree(database: Path, db_preset: RadarPreset, query: Path) -> None:
    """Without ``--preset``, the queries are read with the database's preset; a query folder whose simulator
    metadata records another radar's range grid is refused, naming both recorded presets.

    Raises:
        ConfigError: the two folders were recorded with radars of different range grids.
    """
    recorded = read_sequence_meta(query).get("preset") if Path(query).is_dir() else None
    if recorded is None:
        return
    q_preset = get_preset(recorded)
    if (q_preset.range_resolution_m, q_preset.range_offset_m) == (db_preset.range_resolution_m,
                                                                  db_preset.range_offset_m):
        return
    raise ConfigError(f"the database {database} was recorded with radar preset {db_preset.name!r} and the query "
                      f"{query} with {q_preset.name!r} ({SIM_META_FILE}): read with the database's preset, "
                      f"{range_grid_difference(q_preset, db_preset)}; bench a database and queries of one radar "
                      "(render the query again with `reradar sim --preset " f"{db_preset.name}`)")


def _check_query_names_its_radar(db_preset: RadarPreset, query: Path, layout: str | None) -> None:
    """Without ``--preset``, refuse a query folder that does not record its radar in a layout whose presets differ in
    range geometry (Boreas: boreas / boreas-2021), as ``load_sequence`` refuses such a database: reading it with the
    database's preset would be a guess (QA session 36: boreas-2021 scans read as boreas, Recall@1 5 % without a word).

    Raises:
        ConfigError: naming the folder, the presets it could be, and ``--preset``.
    """
    if not Path(query).is_dir() or read_sequence_meta(query).get("preset") is not None:
        return
    q_layout = layout or detect_layout(query)
    if layout_presets_ambiguous(q_layout):
        raise ConfigError(f"the query {query} does not say which radar recorded it, and {q_layout}-layout radars "
                          f"differ in range geometry: pass the one it was recorded with (--preset; the database's "
                          f"is {db_preset.name!r}, e.g. --preset {db_preset.name} if both are from one radar)")


def query_pair_names(database: Path, queries: list[Path]) -> list[str]:
    """One distinct result name per ``--query`` folder (the key of results.json and of ``per_query/<name>``).

    A folder's name, or, where several query folders share a name (``alt/q`` and ``alt2/q``), its parent
    folders' names joined with ``-`` as far up as it takes to tell them apart (``alt-q``, ``alt2-q``); a query
    named like the database gets ``-query`` appended.

    Raises:
        ConfigError: the same folder given twice as ``--query`` (its results would overwrite each other).
    """
    resolved = [Path(q).resolve() for q in queries]
    seen: dict[Path, Path] = {}
    for given, real in zip(queries, resolved, strict=True):
        if real in seen:
            raise ConfigError(f"--query {given} names the same folder as --query {seen[real]}: give each query "
                              "folder once")
        seen[real] = given
    names = distinct_folder_labels(resolved, sep="-")
    db_name = Path(database).resolve().name
    return [f"{n}-query" if n == db_name else n for n in names]


def suite_spacing(name: str) -> dict[str, int]:
    """Frame step each sequence of suite ``name`` was rendered at (its protocol spacing), by sequence name."""
    from reradar_core.sim.suites import SUITES

    suite = SUITES.get(name)
    return {s.name: s.every for s in suite.sequences} if suite is not None else {}


def pairs_from_suite(name: str, every: int | None = None, limit: int | None = None,
                     progress: bool = True, query_limit: int | None = None, split_at: str | None = None,
                     split_sequence: str | None = None) -> tuple[list[BenchPair], float]:
    """A simulated suite: render (cached) and pair its database with each of its query sequences, or, with
    ``split_at``, split one of its sequences (``split_sequence``, default the database sequence) into
    database and queries.

    Suites are already rendered at their protocol's frame spacing (e.g. every 5th frame off-road), so
    ``every`` defaults to 1 here. Returns the pairs and the suite's radius.
    """
    from reradar_core.sim.suites import build_suite

    data = build_suite(name, progress=progress)
    if not data.database or not data.queries:
        from reradar_core.sim.suites import suite_names

        raise ConfigError(f"suite {name!r} has no database/query sequences (training split?); choose an "
                          f"evaluation suite: {', '.join(suite_names('benchmark'))} (or smoke)")
    if split_at is not None:
        folders = {p.name: p for p in data.database + data.queries}
        target = split_sequence or data.database[0].name
        if target not in folders:
            raise ConfigError(f"--split-sequence {target!r} is not a sequence of suite {name!r}; choose one of "
                              f"{sorted(folders)}")
        pair = split_pair(data.load(folders[target]), parse_split(split_at), every or 1, limit, query_limit)
        return [pair], float(data.radius_m)
    if split_sequence is not None:
        raise ConfigError("--split-sequence needs --split-at")
    if len(data.database) > 1:
        raise ConfigError(f"suite {name!r} has {len(data.database)} database sequences; one is supported")
    db = subsample(data.load(data.database[0]), every or 1, limit)
    pairs = [BenchPair(qp.name, db, subsample(data.load(qp), every or 1, query_limit or limit))
             for qp in data.queries]
    return pairs, float(data.radius_m)
