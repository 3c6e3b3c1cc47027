"""Fit the shipped ``ConfidenceModel`` on training splits (``reradar fit-confidence``).

Data (never a benchmark query sequence): for each target training split (``reradar_core.training.suites``)
its sessions are the queries and the benchmark suite's *database* sequence of that domain is the map - the
same pairing the target-adapted descriptor was trained on. Two kinds of session: the split's training
traversals (the descriptor trained on all but their tails) and its ``confidence`` sessions, which train no
weights - queries like a deployment's, on which a descriptor's landmarks align less than on scans it has
seen (rows marked ``unseen``). Each query is localized by the service's ``Localizer`` with the split's
target-adapted model (``our-3-<domain>``) and the aligned-ratio floor alone at its lowest candidate value
(``PROBE_FLOOR``, ``min_confidence=0``); its label is 1 when the winner's pose is within the paper's success
thresholds (``localization_success``: translation error < R of the suite, heading error < 10 deg), else 0.
Queries are run twice where useful: on the full map, and on a map of the first half of the database keyframes
for the queries that have no keyframe of that half within R - no-match queries, whose every pose is a wrong
answer (labels 0), as a user sees on an unmapped road. The maps hold every scan of the drive as a keyframe
(3.8-6.7 m apart); ``reradar fit-confidence --map-spacings-m 0,12`` adds maps with keyframes 12 m apart (as
``reradar build-map --min-spacing-m 12`` keeps them), each density a group of its own for the bar's wrong-answer
rule (``map_group``). Not the default: fitted on both densities, every agreement cue tried gave more wrong
answers on the held-out tails of both than the fit on the drive's maps alone (docs/MODEL.md, "Sparser maps";
``benchmarks/confidence_map_density.py``).

Held-out split: the last ``holdout`` (15 %) of each query sequence - for the training traversals the tail the
descriptor was validated on and never trained on - gives the reliability numbers (ECE, diagram, wrong-answer
rate at the bar); the rest fits the coefficients and chooses the floor (judged on the unseen sessions) and the
bar (``fit_from_data``). A floor above the probe's is applied through the ``aligned_ratio`` cue: the runs'
deeper search on refusal (``expand_on_refusal``) then ran less often than it would at that floor, which can
only undercount that floor's correct answers. Everything is deterministic (the localizer is seeded, the split
is by position).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from reradar_core.errors import ConfigError
from reradar_core.evaluation.metrics import has_revisit, localization_errors, localization_success
from reradar_core.geometry.se2 import compose
from reradar_core.localization.confidence import (
    CUE_NAMES,
    ConfidenceModel,
    choose_min_confidence,
    choose_min_confidence_by_cost,
    cues_from_result,
    expected_calibration_error,
    fit_confidence_model,
    reliability_bins,
)
from reradar_core.localization.keyframes import select_keyframes

__all__ = ["SPLIT_MODELS", "FitData", "SplitRun", "choose_place_margin", "collect_split", "collection_config",
           "fit_from_data", "label_run",
           "map_group", "plot_reliability", "split_models", "split_runs"]

logger = logging.getLogger(__name__)

#: training split -> the target-adapted model whose answers it judges (width 0.5 since session 16)
SPLIT_MODELS: dict[str, str] = {
    "train-target-boreas": "our-3-boreas-w05",
    "train-target-loop": "our-3-loop-w05",
    "train-target-loop-open": "our-3-loop-w05",
    "train-target-offroad": "our-3-offroad-w05",
}


def split_models(overrides: str = "", splits: list[str] | None = None) -> dict[str, str]:
    """The model whose answers each split judges: ``SPLIT_MODELS`` with ``SPLIT=MODEL`` overrides.

    Args:
        overrides: comma-separated ``SPLIT=MODEL`` pairs (e.g. ``train-target-boreas=our-3-boreas-w05``); a model is
            a shipped name or a ``.pt`` path, checked here (``resolve_weights``).
        splits: the splits to return (default: every key of ``SPLIT_MODELS``).

    Raises:
        ConfigError: a pair without ``=`` or an empty side, a split that is not a key of ``SPLIT_MODELS`` (in a
            pair or in ``splits``), a pair for a split outside ``splits``, a split named twice (in ``splits`` or
            in two pairs), an unknown model, or an empty ``splits``.
    """
    if splits is not None:
        if not splits:
            raise ConfigError("--splits names no training split")
        repeated = sorted({s for s in splits if splits.count(s) > 1})
        if repeated:  # each would be localized again and weigh twice in the fit
            raise ConfigError(f"--splits names {', '.join(repeated)} more than once")
        unknown = [s for s in splits if s not in SPLIT_MODELS]
        if unknown:
            raise ConfigError(f"unknown training split(s) {', '.join(unknown)}; choose from {', '.join(SPLIT_MODELS)}")
    from reradar_core.model.registry import resolve_weights

    out = dict(SPLIT_MODELS)
    given: dict[str, str] = {}
    for item in (t.strip() for t in overrides.split(",")):
        if not item:
            continue
        split, sep, model = (part.strip() for part in item.partition("="))
        if not sep or not split or not model:
            raise ConfigError(f"model override {item!r} is not SPLIT=MODEL")
        if split not in SPLIT_MODELS:
            raise ConfigError(f"model override for unknown split {split!r}; choose from {sorted(SPLIT_MODELS)}")
        if splits is not None and split not in splits:
            raise ConfigError(f"model override for {split!r}, which --splits does not fit ({', '.join(splits)})")
        if split in given:  # the last would win without a word
            raise ConfigError(f"--models names a model for {split!r} twice ({given[split]}, {model}); name one")
        given[split] = model
        resolve_weights(model)  # an unknown name or a missing .pt is said now, not as a cache miss or after a run
        out[split] = model
    return {s: out[s] for s in (splits if splits is not None else out)}


#: the cues' place radius (metres) and agreement count, stored with the fitted model
PLACE_RADIUS_M = 20.0
TOP_N = 5
# What one wrong ``localized`` answer costs, counted in refused correct answers, when the bar is chosen: a
# refusal costs the vehicle one more scan (0.25 s at 4 Hz) before it asks again; a confident wrong pose can pull
# its state estimate hundreds of metres off until something else notices. A product choice, stated, not fitted.
DEFAULT_WRONG_COST = 10.0
#: fewer wrong answers above the floor than this among the fit runs: the bar is not fitted (a warning, no refusal)
MIN_WRONG_FOR_BAR = 10

#: the aligned-landmark floors the fit chooses from (``fit_from_data``); the runs are collected at the lowest
PROBE_FLOOR = 0.25
FLOOR_GRID = (0.25, 0.30, 0.35, 0.40, 0.45, 0.50)
#: the tie margins (``LocalizationConfig.min_place_margin``) the fit chooses from (``choose_place_margin``); the runs
#: are collected at the lowest, a higher one is applied afterwards through the ``margin`` cue (the rule's own measure)
PROBE_PLACE_MARGIN = 0.02
PLACE_MARGIN_GRID = (0.02, 0.03, 0.04, 0.05, 0.06, 0.075, 0.09, 0.10, 0.125)
#: the tie margin may refuse at most this share of the correct answers of the unseen sessions outside periodic worlds
#: (a budget mirroring the issue's 0.5 % of wrong answers: a product choice, stated, not fitted)
MAX_MARGIN_REFUSED_FRACTION = 0.005


def choose_place_margin(d: FitData, model: ConfidenceModel, grid: tuple[float, ...] = PLACE_MARGIN_GRID,
                        max_refused_fraction: float = MAX_MARGIN_REFUSED_FRACTION) -> tuple[float, list[dict[str, Any]]]:
    """The tie margin (``LocalizationConfig.min_place_margin``): among the margins of ``grid`` that refuse at most
    ``max_refused_fraction`` of the correct ``localized`` answers (``model``'s floor and bar) of the fit runs of the
    unseen sessions outside periodic worlds, the smallest that leaves the fewest wrong answers in the periodic worlds'
    fit runs. A wider margin refuses more answers whose place another place screens almost as well: on a street that
    repeats itself most of them are one period off, elsewhere most are right.

    Returns:
        The margin and the table: per margin, on the unseen sessions' fit runs, the wrong and correct answers in
        periodic worlds and elsewhere, and the correct answers elsewhere it refuses.
    """
    aligned = d.cues[:, CUE_NAMES.index("aligned_ratio")]
    margin = d.cues[:, CUE_NAMES.index("margin")]
    p = np.where(d.has_pose, model.predict(d.cues), 0.0)
    answered = d.eligible & (aligned >= model.min_aligned_ratio) & (p >= model.min_confidence)
    judge = d.unseen & ~d.heldout
    per = d.periodic
    base = int((answered & d.correct & judge & ~per).sum())
    table = []
    for t in sorted(grid):
        acc = answered & (margin >= t)
        refused = int((answered & ~acc & d.correct & judge & ~per).sum())
        table.append({"margin": t, "periodic_wrong": int((acc & ~d.correct & judge & per).sum()),
                      "periodic_correct": int((acc & d.correct & judge & per).sum()),
                      "other_wrong": int((acc & ~d.correct & judge & ~per).sum()),
                      "other_correct": int((acc & d.correct & judge & ~per).sum()), "other_refused": refused})
    allowed = [r for r in table if r["other_refused"] <= max_refused_fraction * base] or table[:1]
    fewest = min(r["periodic_wrong"] for r in allowed)
    return next(r["margin"] for r in allowed if r["periodic_wrong"] == fewest), table


@dataclass
class FitData:
    """One row per localization run.

    Attributes:
        cues: (Q, C) float64 cues (``CUE_NAMES`` order; zeros where ``has_pose`` is False).
        has_pose: (Q,) bool the winner has a pose (cues defined).
        correct: (Q,) bool the pose is within the success thresholds (False without a pose).
        eligible: (Q,) bool the answer passes the aligned-ratio floor (``localized`` without the confidence).
        revisit: (Q,) bool the map has a keyframe within R of the query.
        heldout: (Q,) bool the query lies in its sequence's held-out tail.
        split: (Q,) str training split of the row (``SPLIT-lookalike`` for its look-alike sessions' runs).
        unseen: (Q,) bool the query's session trained no weights (a ``confidence`` session of the split).
    """

    cues: np.ndarray
    has_pose: np.ndarray
    correct: np.ndarray
    eligible: np.ndarray
    revisit: np.ndarray
    heldout: np.ndarray
    split: np.ndarray
    unseen: np.ndarray

    def take(self, rows: np.ndarray) -> FitData:
        """The rows selected by ``rows`` ((Q,) bool mask or index array)."""
        return FitData(*(getattr(self, f.name)[rows] for f in fields(FitData)))

    @property
    def periodic(self) -> np.ndarray:
        """(Q,) bool the row's map and session lie in a periodic world (``SPLIT-periodic``)."""
        return np.char.endswith(self.split.astype(str), "-periodic")

    @staticmethod
    def concat(parts: list[FitData]) -> FitData:
        return FitData(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(FitData)))

    def save(self, path: Path) -> None:
        np.savez_compressed(path, **{f.name: getattr(self, f.name) for f in fields(self)})

    @staticmethod
    def load(path: Path) -> FitData:
        z = np.load(path, allow_pickle=False)
        return FitData(*(z[f.name] for f in fields(FitData)))


def _localizer(method: Any, records: list[Any], poses: np.ndarray, config: Any) -> Any:
    from reradar_core.baselines.ours import prepared_to_features
    from reradar_core.localization import InMemoryKeyframes, Localizer
    from reradar_core.retrieval import GlobalIndex

    index = GlobalIndex(np.stack([np.asarray(r["global"], np.float32).reshape(-1) for r in records]))
    keyframes = InMemoryKeyframes(lambda j: prepared_to_features(records[j]), poses,
                                  np.array([int(np.asarray(r["timestamp_us"])) for r in records]))
    return Localizer(index, keyframes, config)


@dataclass
class SplitRun:
    """One localization of the pairing (module docstring): a query of a session on the full or the half map.

    Attributes:
        features: the query's ``ScanFeatures``.
        T_map_query: (3,) float64 ground truth at the query's mid-sweep time (x m, y m, yaw rad).
        revisit: the map has a keyframe within the suite's radius of the query.
        map_name: ``full`` (the whole database drive) or ``half`` (its first half; no-match queries only).
        localizer: the ``Localizer`` of that map.
        index: the query's position in its (subsampled) session; session_size: the session's length.
        unseen: the session is a ``confidence`` session (no weight trained on it).
        lookalike: the session was driven in the split's look-alike world (``sim.suites.lookalike_suite``): the
            map's roads, other surroundings, so no map keyframe shows its place (``revisit`` False).
        periodic: the session and the map were driven in the split's periodic world (``sim.suites.periodic_suite``:
            one tile layout everywhere, so a street repeats every 40 m); labelled by ground truth like the others.
    """

    features: Any
    T_map_query: np.ndarray
    revisit: bool
    map_name: str
    localizer: Any
    index: int
    session_size: int
    unseen: bool
    lookalike: bool = False
    periodic: bool = False

    @property
    def group(self) -> str:
        """Suffix of the run's ``FitData.split`` label: ``-lookalike``, ``-periodic`` or empty."""
        return "-lookalike" if self.lookalike else "-periodic" if self.periodic else ""


def split_runs(split: str, method: Any, config: Any, query_step: int = 1,
               progress: bool = True, map_spacing_m: float = 0.0,
               lookalike: bool = False, periodic: bool = False) -> tuple[float, Iterator[SplitRun]]:
    """The pairing's localizations of one split, in a fixed order: for each session (training traversals, then
    ``confidence`` sessions), every query on the full map, then the no-match queries on the half map; with
    ``lookalike``, then every query of the split's look-alike sessions (``sim.suites.lookalike_suite``: its
    ``confidence`` sessions driven on the same roads in a world of another seed) on the full map, none a revisit;
    with ``periodic``, then every query of the split's ``confidence`` sessions driven in its periodic world
    (``sim.suites.periodic_suite``) on the map drive of that world.

    Args:
        split: a key of ``SPLIT_MODELS`` (``TRAINING_SPLITS`` names its benchmark domain).
        method: the ``Ours`` method whose features and localizers are used.
        config: the ``LocalizationConfig`` the localizers are built with.
        query_step: use every ``query_step``-th query scan (1 = all).
        progress: progress bars.
        map_spacing_m: keep a database scan as a keyframe of both maps only this far (metres) from the last
            kept one (``select_keyframes``, as ``reradar build-map --min-spacing-m``); 0 = every scan.
        lookalike: add the look-alike sessions' runs (rendered on first use).
        periodic: add the periodic world's runs (rendered on first use).

    Returns:
        The suite's radius (metres) and the runs (a generator: features are computed session by session).
    """
    from reradar_core.benchmark.runner import BenchConfig, prepare_sequence
    from reradar_core.sim.suites import build_suite
    from reradar_core.training.suites import TRAINING_SPLITS

    data = build_suite(split, progress=progress)
    look = build_suite(f"{split}-lookalike", progress=progress) if lookalike else None
    per = build_suite(f"{split}-periodic", progress=progress) if periodic else None
    bench_name = TRAINING_SPLITS[split]
    assert bench_name is not None
    bench = build_suite(bench_name, progress=progress)
    radius = bench.radius_m
    bc = BenchConfig(radius_m=radius, rotation_stress=False, progress=progress)

    def runs() -> Iterator[SplitRun]:
        from tqdm import tqdm

        from reradar_core.baselines.ours import prepared_to_features

        def map_drive(suite: Any) -> tuple[list[Any], np.ndarray]:
            """The suite's map drive: the kept keyframes' records and mid-sweep poses."""
            db_seq = suite.load(suite.database[0])
            db = prepare_sequence([method], db_seq, bc)[method.name]
            db_poses = db_seq.mid_sweep_poses()  # keyframe poses at mid-sweep, as in a map (docs/CONVENTIONS.md)
            keep = select_keyframes(db_poses, map_spacing_m)
            return [db.records[int(i)] for i in keep], db_poses[keep]

        records, db_poses = map_drive(bench)
        half = len(records) // 2
        maps = {"full": (_localizer(method, records, db_poses, config), db_poses),
                "half": (_localizer(method, records[:half], db_poses[:half], config), db_poses[:half])}
        sessions = [(p, False) for p in data.training] + [(p, True) for p in data.confidence]
        for qpath, unseen in sessions:
            qseq = data.load(qpath).subset(slice(None, None, query_step))
            q = prepare_sequence([method], qseq, bc)[method.name]
            gt = qseq.mid_sweep_poses()
            n = len(q.records)
            for map_name, (loc, poses) in maps.items():
                revisit = has_revisit(gt, poses, radius)
                # the half map serves the no-match queries only (a revisit there repeats the full map's)
                todo = np.arange(n) if map_name == "full" else np.flatnonzero(~revisit)
                for i in tqdm(todo, desc=f"{split}/{qseq.name} on the {map_name} map", disable=not progress,
                              leave=False):
                    yield SplitRun(prepared_to_features(q.records[int(i)]), gt[int(i)], bool(revisit[i]), map_name,
                                   loc, int(i), n, unseen)
        for qpath in look.confidence if look is not None else []:
            # the map's roads in another world: near a keyframe by position, but not at its place
            qseq = look.load(qpath).subset(slice(None, None, query_step))
            q = prepare_sequence([method], qseq, bc)[method.name]
            gt = qseq.mid_sweep_poses()
            n = len(q.records)
            loc = maps["full"][0]
            for i in tqdm(range(n), desc=f"{split}/{qseq.name} (look-alike world) on the full map",
                          disable=not progress, leave=False):
                yield SplitRun(prepared_to_features(q.records[i]), gt[i], False, "full", loc, i, n, True, True)
        if per is not None:
            # a world whose streets repeat every tile: the map and the sessions both drive it
            p_records, p_poses = map_drive(per)
            p_loc = _localizer(method, p_records, p_poses, config)
            for qpath in per.confidence:
                qseq = per.load(qpath).subset(slice(None, None, query_step))
                q = prepare_sequence([method], qseq, bc)[method.name]
                gt = qseq.mid_sweep_poses()
                n = len(q.records)
                revisit = has_revisit(gt, p_poses, radius)
                for i in tqdm(range(n), desc=f"{split}/{qseq.name} (periodic world) on its map",
                              disable=not progress, leave=False):
                    yield SplitRun(prepared_to_features(q.records[i]), gt[i], bool(revisit[i]), "full", p_loc, i, n,
                                   True, periodic=True)

    return radius, runs()


def collection_config(min_inlier_ratio: float = PROBE_FLOOR) -> Any:
    """The ``LocalizationConfig`` of the fit's runs: no confidence bar, the aligned-ratio floor at
    ``min_inlier_ratio`` and the tie margin at ``PROBE_PLACE_MARGIN`` (a higher floor or margin is applied afterwards
    through their cues), no repeated-place check (``max_place_repetition`` None: chosen on such runs itself), and
    the rigid registration's poses (no motion compensation: the cues a served answer is judged on are the rigid
    registration's, ``Localizer._final_pose``, and a label computed from the same pose keeps them paired)."""
    from reradar_core.localization.pipeline import LocalizationConfig
    from reradar_core.matching.motion import MotionConfig

    return replace(LocalizationConfig(), min_confidence=0.0, min_inlier_ratio=min_inlier_ratio,
                   min_place_margin=PROBE_PLACE_MARGIN, max_place_repetition=None,
                   motion=MotionConfig(enabled=False))


def collect_split(split: str, query_step: int = 1, holdout: float = 0.15, progress: bool = True,
                  min_inlier_ratio: float = PROBE_FLOOR, model: str | None = None,
                  map_spacing_m: float = 0.0, lookalike: bool = False, periodic: bool = False) -> FitData:
    """Localize the split's sessions on its domain's map and label the answers (module docstring).

    Both kinds of session run: the split's training traversals (the model trained on all but their tails) and
    its ``confidence`` sessions (no weight trained on them; rows marked ``unseen``).

    Args:
        split: a key of ``SPLIT_MODELS``.
        query_step: use every ``query_step``-th query scan (1 = all).
        holdout: fraction at the end of each query sequence held out for the reliability numbers.
        progress: progress bars.
        min_inlier_ratio: the aligned-landmark floor of the runs; the lowest floor the fit may choose
            (``PROBE_FLOOR``): a higher floor is applied afterwards through the ``aligned_ratio`` cue.
        model: the model whose answers are judged (default: the split's ``SPLIT_MODELS`` entry).
        map_spacing_m: the map's keyframe spacing (``split_runs``); the rows of a sparser map than the drive's
            are labelled ``SPLIT@Nm`` (``map_group``), so the bar holds on them on their own.
        lookalike: add the split's look-alike sessions (``split_runs``), labelled ``SPLIT-lookalike`` (a group
            of their own for the bar: every answer there is wrong).
        periodic: add the split's periodic world (``split_runs``), labelled ``SPLIT-periodic`` (a group of its own).
    """
    from reradar_core.baselines.ours import Ours

    # the floor and the tie margin alone, at their lowest candidate values: every answer is labelled (the
    # repeated-place check off: it is chosen on runs like these, ``benchmarks/place_repetition.py``)
    config = collection_config(min_inlier_ratio)
    method = Ours(model or SPLIT_MODELS[split], localization=config)
    radius, runs = split_runs(split, method, config, query_step, progress, map_spacing_m, lookalike, periodic)
    rows, groups = [], []
    for run in runs:
        rows.append(label_run(run, run.localizer.localize(run.features, config), radius, holdout))
        groups.append(map_group(split + run.group, map_spacing_m))
    m = len(rows)
    cols = list(zip(*rows, strict=True)) if rows else [()] * 7
    return FitData(np.array(cols[0], np.float64).reshape(m, len(CUE_NAMES)),
                   *(np.array(c, bool) for c in cols[1:6]), np.array(groups, dtype=str).reshape(m),
                   np.array(cols[6], bool))


def label_run(run: SplitRun, res: Any, radius_m: float,
              holdout: float) -> tuple[np.ndarray, bool, bool, bool, bool, bool, bool]:
    """One ``FitData`` row (``cues``, ``has_pose``, ``correct``, ``eligible``, ``revisit``, ``heldout``,
    ``unseen``) of a run's ``LocalizationResult`` ``res``: correct = the winner's pose within the success
    thresholds (``radius_m``, 10 deg) of a revisit query."""
    cues = cues_from_result(res, PLACE_RADIUS_M, TOP_N)
    ok = False
    if cues is not None:
        assert res.best is not None and res.best.T_keyframe_query is not None
        est = np.asarray(compose(res.best.T_map_keyframe, res.best.T_keyframe_query))[None]
        e_t, e_r = localization_errors(est, run.T_map_query[None])
        ok = bool(localization_success(e_t, e_r, radius_m)[0]) and run.revisit
    return (cues.as_array() if cues is not None else np.zeros(len(CUE_NAMES)), cues is not None, ok,
            bool(res.localized), run.revisit, run.index >= (1.0 - holdout) * run.session_size, run.unseen)


def map_group(split: str, map_spacing_m: float) -> str:
    """The ``FitData.split`` label of a split's runs on its map with keyframes ``map_spacing_m`` apart."""
    return split if map_spacing_m <= 0 else f"{split}@{map_spacing_m:g}m"


def _rates(p: np.ndarray, d: FitData, eligible: np.ndarray, mask: np.ndarray, bar: float) -> dict[str, float]:
    """Wrong / correct ``localized`` answers (percent of the runs in ``mask``) with and without the bar."""
    n = max(int(mask.sum()), 1)
    old = eligible & mask
    new = old & (p >= bar)
    return {"runs": int(mask.sum()),
            "wrong_pct_floor_only": 100.0 * float((old & ~d.correct).sum()) / n,
            "wrong_pct_with_bar": 100.0 * float((new & ~d.correct).sum()) / n,
            "correct_pct_floor_only": 100.0 * float((old & d.correct).sum()) / n,
            "correct_pct_with_bar": 100.0 * float((new & d.correct).sum()) / n}


def fit_from_data(d: FitData, l2: float = 1.0, max_wrong_fraction: float = 0.005,
                  meta: dict[str, Any] | None = None,
                  wrong_cost: float | None = DEFAULT_WRONG_COST,
                  floors: tuple[float, ...] = FLOOR_GRID) -> tuple[ConfidenceModel, dict[str, Any]]:
    """Fit on the non-held-out runs with a pose, choose the floor and the bar there, report on the held-out runs.

    For each candidate aligned-landmark floor (``floors``, each at least the runs' probe floor) the bar is the
    higher of two, both on the fit runs: the lowest at which wrong answers are at most ``max_wrong_fraction``
    of the runs of *every* split and of each split's unseen sessions on their own (``choose_min_confidence``
    per group: the issue's target holds per suite, not pooled), and the one that minimises ``wrong_cost`` x
    wrong answers + refused correct answers (``choose_min_confidence_by_cost``; None: not used). The floor is
    the one whose (floor, bar) pair costs least - ``wrong_cost`` x wrong + correct poses left unanswered - on
    the fit runs of the unseen sessions (all fit runs when there are none): queries like a deployment's, which
    the descriptor never trained on. Ties go to the higher floor.

    Runs in periodic worlds (``SPLIT-periodic``) choose the tie margin only (``choose_place_margin``, reported as
    ``place_margin``): on a street that repeats itself a right and a wrong answer differ in no cue but the margin,
    and fitted with the others they tilt every weight towards it (session 26: the bar rose from 0.77 to 0.92 and
    refused 3 % of the right answers elsewhere).

    Returns:
        The model (its ``meta`` holds the report; ``min_aligned_ratio`` the floor, ``min_confidence`` the bar)
        and the report: sizes, ECE (10 bins) on the held-out runs with a pose, the per-floor table, wrong /
        correct answer rates (percent of runs) with the floor alone and with the bar.
    """
    if d.periodic.any():
        own, own_report = fit_from_data(d.take(~d.periodic), l2, max_wrong_fraction, meta, wrong_cost, floors)
        chosen, table = choose_place_margin(d, own)
        own_report["place_margin"] = {"chosen": chosen, "probe": PROBE_PLACE_MARGIN,
                                      "max_refused_fraction": MAX_MARGIN_REFUSED_FRACTION, "table": table,
                                      "periodic_runs": int(d.periodic.sum())}
        return replace(own, meta={**own.meta, "report": own_report}), own_report
    fit_rows = d.has_pose & ~d.heldout
    model = fit_confidence_model(d.cues[fit_rows], d.correct[fit_rows], l2=l2, place_radius_m=PLACE_RADIUS_M,
                                 top_n=TOP_N)
    p = np.where(d.has_pose, model.predict(d.cues), 0.0)
    fit_all = ~d.heldout
    aligned = d.cues[:, CUE_NAMES.index("aligned_ratio")]
    judge = fit_all & d.unseen if (fit_all & d.unseen).any() else fit_all
    groups = {f"{s}{'/unseen' if u else ''}": fit_all & (d.split == s) & (d.unseen == u)
              for s in np.unique(d.split) for u in (False, True)}
    groups = {g: rows for g, rows in groups.items() if rows.any()}

    def choose(floor: float) -> dict[str, Any]:
        el = d.eligible & (aligned >= floor)
        per_group = {g: choose_min_confidence(p[r], d.correct[r], el[r], int(r.sum()), max_wrong_fraction)
                     for g, r in groups.items()}
        bar_cost = (choose_min_confidence_by_cost(p[fit_all], d.correct[fit_all], el[fit_all], wrong_cost)
                    if wrong_cost is not None else 0.0)
        bar = max([bar_cost, *per_group.values()])
        acc = el & (p >= bar)
        wrong = int((acc & ~d.correct & judge).sum())
        unanswered = int((d.correct & ~acc & judge).sum())
        return {"floor": floor, "bar": bar, "bar_cost": bar_cost, "bar_max_wrong_per_group": per_group,
                "eligible": el, "judged_correct": int((acc & d.correct & judge).sum()), "judged_wrong": wrong,
                "judged_cost": (wrong_cost or 1.0) * wrong + unanswered}

    table = [choose(f) for f in sorted(floors, reverse=True)]
    best = table[0]
    for row in table[1:]:
        if row["judged_cost"] < best["judged_cost"]:  # strictly better: ties keep the higher floor
            best = row
    floor, bar, el = best["floor"], best["bar"], best["eligible"]
    ho = d.has_pose & d.heldout
    kinds = {"training sessions": ~d.unseen, "unseen sessions": d.unseen}
    report: dict[str, Any] = {
        "runs": int(len(d.correct)), "fit_runs_with_pose": int(fit_rows.sum()),
        "fit_positives": int(d.correct[fit_rows].sum()), "heldout_runs_with_pose": int(ho.sum()),
        "heldout_positives": int(d.correct[ho].sum()), "unseen_runs": int(d.unseen.sum()),
        "ece_heldout": expected_calibration_error(p[ho], d.correct[ho]),
        "ece_fit": expected_calibration_error(p[fit_rows], d.correct[fit_rows]),
        "ece_heldout_above_floor": expected_calibration_error(p[ho & el], d.correct[ho & el]),
        "heldout_runs_above_floor": int((ho & el).sum()),
        "max_wrong_fraction": max_wrong_fraction, "wrong_cost": wrong_cost,
        "floors": [{k: v for k, v in r.items() if k != "eligible"} for r in table],
        "min_aligned_ratio": floor, "min_confidence": bar,
        "bar_max_wrong_per_group": best["bar_max_wrong_per_group"], "bar_cost": best["bar_cost"],
        "fit": _rates(p, d, el, ~d.heldout, bar), "heldout": _rates(p, d, el, d.heldout, bar),
        "per_split_heldout": {f"{s}, {k}": _rates(p, d, el, d.heldout & (d.split == s) & m, bar)
                              for s in np.unique(d.split) for k, m in kinds.items()
                              if (d.heldout & (d.split == s) & m).any()},
    }
    wrong_above = int((el & ~d.correct & fit_all).sum())
    if wrong_above < MIN_WRONG_FOR_BAR:  # the bar is then not fitted but whatever the rules return on no evidence
        warning = (f"only {wrong_above} wrong answer(s) above the aligned-landmark floor among the {int(fit_all.sum())} "
                   f"fit runs (fewer than {MIN_WRONG_FOR_BAR}): too few wrong answers to fit a confidence bar, so "
                   f"min_confidence = {bar:.3g} is not supported by data; fit on more runs (whole training splits) "
                   "before using this model")
        logger.warning("%s", warning)
        report["warnings"] = [warning]
    full_meta = {**(meta or {}), "report": report}
    model = replace(model, min_confidence=bar, min_aligned_ratio=floor, meta=full_meta)
    return model, report


def plot_reliability(curves: dict[str, tuple[np.ndarray, np.ndarray]], path: Path, title: str,
                     bins: int = 10, bar: float | None = None) -> None:
    """Reliability diagram: per curve (label -> (confidence (Q,), correct (Q,) bool)) the observed fraction of
    correct poses per confidence bin against the bin's mean confidence; the bins' counts below (log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, axh) = plt.subplots(2, 1, figsize=(5.5, 6.5), gridspec_kw={"height_ratios": [3, 1]}, sharex=True)
    ax.plot([0, 1], [0, 1], "--", color="grey", label="perfect calibration")
    width = 1.0 / bins / (len(curves) + 1)
    for k, (label, (p, y)) in enumerate(curves.items()):
        t = reliability_bins(p, y, bins)
        ok = t["count"] > 0
        ax.plot(t["mean_p"][ok], t["frac_pos"][ok], "o-", label=f"{label} (n={len(p)})")
        axh.bar(t["edges"][:-1] + (k + 0.5) * width + 0.5 * width, t["count"], width=width, label=label)
    if bar is not None:
        ax.axvline(bar, color="tab:red", lw=1, label=f"min_confidence {bar:.2f}")
    ax.set_ylabel("observed fraction within thresholds")
    ax.set_xlim(0, 1)
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(title, fontsize=9)
    ax.legend(loc="upper left", fontsize=8)
    axh.set_yscale("log")
    axh.set_xlabel("confidence (predicted probability)")
    axh.set_ylabel("runs per bin")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
