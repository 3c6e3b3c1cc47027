"""Which sequences a benchmark compares: a simulated suite (``reradar_core.sim.suites``) or real folders."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reradar_core.benchmark.runner import BenchPair
from reradar_core.errors import ConfigError
from reradar_core.io.datasets import Sequence, load_sequence

__all__ = ["subsample", "pairs_from_folders", "pairs_from_suite", "default_radius"]


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
                       every: int = 5, limit: int | None = None,
                       query_limit: int | None = None) -> tuple[list[BenchPair], float]:
    """Real recordings: one database folder and query folders in their dataset layouts.

    ``limit`` caps every sequence, ``query_limit`` only the query sequences (evenly spread)."""
    db = subsample(load_sequence(database, layout, preset), every, limit)
    pairs = []
    for q in queries:
        qs = subsample(load_sequence(q, layout, preset or db.preset.name), every, query_limit or limit)
        name = qs.name if qs.name != db.name else f"{qs.name}-query"
        pairs.append(BenchPair(name, db, qs))
    return pairs, default_radius(db.preset.name)


def pairs_from_suite(name: str, every: int | None = None, limit: int | None = None,
                     progress: bool = True, query_limit: int | None = None) -> tuple[list[BenchPair], float]:
    """A simulated suite: render (cached) and pair its database with each of its query sequences.

    Suites are already rendered at their protocol's frame spacing (e.g. every 5th frame off-road), so
    ``every`` defaults to 1 here. Returns the pairs and the suite's radius.
    """
    from reradar_core.sim.suites import build_suite

    data = build_suite(name, progress=progress)
    if not data.database or not data.queries:
        raise ConfigError(f"suite {name!r} has no database/query sequences (training split?); "
                          "choose an evaluation suite: smoke, boreas-sim, loop-sim, offroad-sim")
    if len(data.database) > 1:
        raise ConfigError(f"suite {name!r} has {len(data.database)} database sequences; one is supported")
    db = subsample(data.load(data.database[0]), every or 1, limit)
    pairs = [BenchPair(qp.name, db, subsample(data.load(qp), every or 1, query_limit or limit))
             for qp in data.queries]
    return pairs, float(data.radius_m)
