"""Training data plans on the simulator's suites (``reradar_core.sim.suites``): what trains, what validates.

The paper's settings, adapted to offline simulated data (docs/MODEL.md):

- ``train-source`` (stage 1, "Our (1)"): synthetic looped routes in worlds not used by any benchmark suite.
  Each sequence lives in its own world (own place group); the last sequence (``src5``, off-road in rain) is
  held out: its first lap is the validation database, its second lap the validation queries.
- ``train-target-<domain>`` (stage 2, "Our (2)/(3)"): the split's own traversal plus the benchmark suite's
  *database* (map) sequence of that domain — a deployment always has its map, never its future queries. Both
  share the domain's world frame (one place group). The last ``holdout`` fraction of both sequences (the
  end of the route) is held out: map tail = validation database, split tail = validation queries. Query
  sequences of the benchmark suites are never read.
- ``smoke``: the smoke suite's two traversals, training and validating on the same data (a plumbing check,
  never a shipped model).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from reradar_core.errors import ConfigError

__all__ = ["SeqSpec", "TrainingPlan", "suite_training_data", "TRAINING_SPLITS"]

# training split -> benchmark suite whose database shares the world
TRAINING_SPLITS = {
    "train-source": None,
    "train-target-boreas": "boreas-sim",
    "train-target-loop": "loop-sim",
    "train-target-loop-open": "loop-sim-hard",
    "train-target-offroad": "offroad-sim",
    "smoke": None,
}


@dataclass(frozen=True)
class SeqSpec:
    """A sequence folder, its place group and the fraction range [start, stop) of its scans used; ``preset`` and
    ``time_unit`` as ``reradar_core.io.datasets.load_sequence`` takes them (None: the folder's own)."""

    path: Path
    group: str
    start: float = 0.0
    stop: float = 1.0
    preset: str | None = None
    time_unit: str | None = None


@dataclass
class TrainingPlan:
    train: list[SeqSpec] = field(default_factory=list)
    val: list[tuple[SeqSpec, SeqSpec]] = field(default_factory=list)
    note: str = ""
    radius_m: float = 20.0


def suite_training_data(split: str, holdout: float = 0.15, progress: bool = True) -> TrainingPlan:
    """Render (if needed) and describe the data of a training split; see the module docstring."""
    from reradar_core.sim.suites import build_suite

    if split not in TRAINING_SPLITS:
        raise ConfigError(f"unknown training split {split!r}; choose one of {sorted(TRAINING_SPLITS)}")
    data = build_suite(split, progress=progress)
    plan = TrainingPlan(radius_m=data.radius_m)
    if split == "train-source":
        seqs = sorted(data.training)
        held = seqs[-1]
        plan.train = [SeqSpec(p, f"source:{p.name}") for p in seqs[:-1]]
        plan.val = [(SeqSpec(held, "val", 0.0, 0.5), SeqSpec(held, "val", 0.5, 1.0))]
        plan.note = (f"stage 1 source domain: {', '.join(p.name for p in seqs[:-1])}; validation: {held.name} "
                     "lap 1 (database) vs lap 2 (queries)")
        return plan
    if split == "smoke":
        g = "smoke"
        plan.train = [SeqSpec(data.database[0], g), SeqSpec(data.queries[0], g)]
        plan.val = [(SeqSpec(data.database[0], g), SeqSpec(data.queries[0], g))]
        plan.note = "smoke suite (plumbing check: trains and validates on the same two traversals)"
        return plan
    bench = build_suite(TRAINING_SPLITS[split], progress=progress)
    g = f"world:{bench.name}"
    cut = 1.0 - holdout
    own = sorted(data.training)
    db = bench.database[0]
    plan.train = [SeqSpec(t, g, 0.0, cut) for t in own] + [SeqSpec(db, g, 0.0, cut)]
    plan.val = [(SeqSpec(db, g, cut, 1.0), SeqSpec(t, g, cut, 1.0)) for t in own]
    plan.radius_m = bench.radius_m
    names = ", ".join(t.name for t in own)
    plan.note = (f"stage 2 target domain {bench.name}: {names} + the map sequence {db.name} (first "
                 f"{cut:.0%} of each); validation on the held-out last {holdout:.0%} (map tail vs each "
                 "traversal's tail); query sequences never used")
    return plan
