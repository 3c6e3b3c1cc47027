"""``Localizer``: the product's one operation, retrieve -> screen -> verify, over one map.

The service (``maps.database.MapDatabase``), the benchmark's ``Ours`` and the stage timings all call it, so
every number the benchmark reports is measured on the service's code path.

    localizer = Localizer(GlobalIndex(global_descriptors), keyframes, LocalizationConfig())
    result = localizer.localize(features)            # global localization
    result.T_map_query, result.alignment_score, result.candidates
    result = localizer.track(features, PosePrior(T_map_prior, sigma_xy_m=2.0, sigma_yaw_rad=0.05))  # tracking
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Any, TypeVar

import numpy as np

from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.se2 import compose, wrap_angle
from reradar_core.localization.confidence import confidence_cues, default_confidence_model, tracked_cues
from reradar_core.localization.keyframes import KeyframeCache, KeyframeSource
from reradar_core.localization.pipeline import (
    REASON_AMBIGUOUS,
    REASON_INCONSISTENT,
    REASON_TOO_FEW_INLIERS,
    Candidate,
    CandidateVerification,
    LocalizationConfig,
    LocalizationResult,
    localize,
)
from reradar_core.localization.repetition import (
    PlaceRepetition,
    RepetitionTable,
    default_repetition_workers,
    distances_from,
    place_repetition,
    repetition_key,
    repetition_keyframes,
    repetition_settings,
)
from reradar_core.localization.tracking import (
    PosePrior,
    register_from_prior,
    relative_to_keyframe,
    tracking_candidates,
    within_gate,
)
from reradar_core.matching import count_aligned
from reradar_core.matching.kernels import warm_up
from reradar_core.matching.motion import MotionConfig, deskewed, keyframe_twists, motion_polish
from reradar_core.matching.uncertainty import registration_covariance, rotate_covariance
from reradar_core.retrieval import GlobalIndex, similarity_to_distance

_Item = TypeVar("_Item")

__all__ = ["Localizer", "Retrieval"]

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Retrieval:
    """One retrieved keyframe: id, timestamp (us), map pose ``T_map_keyframe`` (x m, y m, yaw rad), Euclidean
    distance between unit global descriptors in [0, 2], 0-based rank."""

    keyframe_id: int
    timestamp_us: int
    T_map_keyframe: np.ndarray
    descriptor_distance: float
    rank: int


class Localizer:
    """Global localization of one scan's features on one map.

    Args:
        index: ``GlobalIndex`` over the keyframes' (N, D) unit global descriptors (row i = keyframe i).
        keyframes: the keyframes' poses, timestamps and features (``KeyframeSource``).
        config: default settings of ``localize`` (a call may pass its own, with the same ``alignment``: the cached
            screen data are built with this one's).
        cache_size: keyframes whose features and compact screen data stay in memory between queries (LRU,
            ~50 KB each); None = the whole map.
        preload: read every keyframe now when the map fits in the cache, so that no query pays for a cold
            read (~1.3 ms each).
    """

    def __init__(self, index: GlobalIndex, keyframes: KeyframeSource,
                 config: LocalizationConfig | None = None, cache_size: int | None = None,
                 preload: bool = False) -> None:
        if index.size != len(keyframes):
            raise ConfigError(f"index holds {index.size} descriptors but the map has {len(keyframes)} keyframes")
        self.index = index
        self.keyframes = keyframes
        self.config = config or LocalizationConfig()
        self.cache = KeyframeCache(keyframes, self.config.alignment, max_cached=cache_size)
        # properties of the map alone, so any query may fill them, under one lock: each keyframe's place repetition
        # per settings (``place_repetition``), whole tables measured beforehand (a map's stored one,
        # ``adopt_repetitions``) per settings, and the keyframes' motion on the map drive per settings (``keyframe_twists``)
        self._cache_lock = threading.Lock()
        self._repetition: dict[tuple, PlaceRepetition] = {}
        self._repetition_tables: dict[tuple, RepetitionTable] = {}
        self._twists: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}
        self._local_dim: int | None = None  # the keyframes' local descriptor length, read on the first query
        warm_up()  # the compiled kernels (numba) are compiled or loaded now, not in the first query
        if preload:
            self.cache.preload()

    def __len__(self) -> int:
        return len(self.keyframes)

    def retrieve(self, global_descriptor: np.ndarray, k: int) -> list[Retrieval]:
        """Top-``k`` keyframes by global descriptor, best first.

        Raises:
            ConfigError: the descriptor's length differs from the map's D.
        """
        g = np.asarray(global_descriptor, np.float32).reshape(-1)
        if g.shape[0] != self.index.dim:
            raise ConfigError(f"query descriptor has {g.shape[0]} values but the map stores {self.index.dim}")
        idx, sims = self.index.search(g, k)
        dists = similarity_to_distance(sims[0])
        poses, ts = self.keyframes.poses, self.keyframes.timestamps_us
        return [Retrieval(int(i), int(ts[i]), poses[i].copy(), float(d), rank)
                for rank, (i, d) in enumerate(zip(idx[0], dists, strict=True)) if i >= 0]

    def localize(self, features: ScanFeatures, config: LocalizationConfig | None = None) -> LocalizationResult:
        """Retrieve ``config.num_to_retrieve`` candidates, screen and verify them (``localization.localize``).

        Returns:
            ``LocalizationResult``; ``timings_ms`` gains ``retrieve_ms`` (FAISS search) and ``read_ms``
            (keyframe reads and landmark grids, cached per keyframe).
        """
        self._check_features(features, "Localizer.localize")
        config = self._call_config(config)
        t0 = time.perf_counter()
        hits = self.retrieve(features.global_descriptor, config.num_to_retrieve)
        t1 = time.perf_counter()
        read_s = [0.0]

        def timed(fetch: Callable[[int], _Item], keyframe_id: int) -> Callable[[], _Item]:
            """``fetch(keyframe_id)`` from the cache on first use, its time added to the read stage."""
            def load() -> _Item:
                t = time.perf_counter()
                item = fetch(keyframe_id)
                read_s[0] += time.perf_counter() - t
                return item
            return load

        wanted = hits if config.rerank else hits[:1]
        candidates = [self._candidate(h.keyframe_id, h.rank, h.descriptor_distance, timed) for h in wanted]
        result = localize(features, candidates, config)
        result.timings_ms["retrieve_ms"] = (t1 - t0) * 1e3
        result.timings_ms["read_ms"] = read_s[0] * 1e3
        bar = config.max_place_repetition
        if result.localized and config.checks_place_repetition and bar is not None and result.best is not None:
            t2 = time.perf_counter()
            repetition = self.place_repetition(result.best.keyframe_id, config).ratio
            result.timings_ms["repetition_ms"] = (time.perf_counter() - t2) * 1e3
            if repetition >= bar:
                # the winner's place repeats on the map: the scan fits the other copy as well (``max_place_repetition``)
                result = replace(result, status="not_localized", reason=REASON_AMBIGUOUS, T_map_query=None)
        return self._final_pose(features, result, config)

    def _check_features(self, features: object, what: str) -> None:
        """``ConfigError`` unless ``features`` are a ``ScanFeatures`` whose local descriptors have the map's length
        (another model's, e.g. 16 against 32 channels, failed in the screen as a numpy broadcast error)."""
        if not isinstance(features, ScanFeatures):
            raise ConfigError(f"{what} takes a scan's ScanFeatures (DescriptorExtractor.describe(scan)), "
                              f"got {type(features).__name__}")
        if self._local_dim is None and len(self):
            self._local_dim = int(self.cache.get(0).features.local_descriptors.shape[1])
        got = int(features.local_descriptors.shape[1])
        if self._local_dim is not None and len(features.keypoints_xy_m) and got != self._local_dim:
            raise ConfigError(f"query local descriptors have {got} values but the map's have {self._local_dim}: "
                              "describe the scan with the map's model")

    def _call_config(self, config: LocalizationConfig | None) -> LocalizationConfig:
        """A call's settings: its own, or the Localizer's. The alignment settings are the Localizer's: its cached
        screen data (landmark grids, alignment masks) were made with them, so a call with other ones would be
        judged half by each (or fail in the grid look-up)."""
        if config is None:
            return self.config
        if not isinstance(config, LocalizationConfig):
            raise ConfigError(f"config must be a LocalizationConfig, got {type(config).__name__}")
        if config.alignment != self.config.alignment:
            raise ConfigError("a call's alignment settings differ from the Localizer's, whose cached screen data "
                              "were built with them: build a Localizer with that LocalizationConfig instead")
        return config

    def keyframe_twists(self, config: MotionConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Every keyframe's motion on the map drive (``matching.motion.keyframe_twists``: (N, 3) vx m/s, vy m/s, yaw
        rate rad/s, and (N,) known), computed once per map and settings."""
        mc = config or self.config.motion
        key = (mc.max_keyframe_gap_s, mc.max_speed_mps, mc.max_yaw_rate_radps)
        with self._cache_lock:
            got = self._twists.get(key)
        if got is None:
            got = keyframe_twists(np.asarray(self.keyframes.poses, np.float64),
                                  np.asarray(self.keyframes.timestamps_us, np.int64), mc)
            with self._cache_lock:
                self._twists[key] = got
        return got

    def _final_pose(self, features: ScanFeatures, result: LocalizationResult, config: LocalizationConfig,
                    query_twist: np.ndarray | None = None) -> LocalizationResult:
        """``result`` (when localized) with its pose motion-compensated (``matching.motion.motion_polish``: when the
        compensation is on and the winning keyframe's motion on the map is known) and its covariance
        (``matching.uncertainty.registration_covariance`` on the final pose's landmark pairs, de-skewed as the pose
        is; in the map frame). The decision, confidence and cues stay the rigid registration's. ``query_twist``:
        the vehicle's own motion (a tracked scan's odometry, ``PosePrior.twist``), the fit's prior instead of the map
        drive's speed. ``timings_ms["motion_ms"]`` and ``["covariance_ms"]``."""
        mc, cc = config.motion, config.covariance
        best = result.best
        if (not (mc.enabled or cc.enabled) or not result.localized or best is None
                or best.T_keyframe_query is None):
            return result
        kid = best.keyframe_id
        src = np.asarray(features.keypoints_xy_m, np.float64)
        dst = self.cache.get(kid).features.keypoints_xy_m
        T_keyframe_query = np.asarray(best.T_keyframe_query, np.float64)
        polished = None
        if mc.enabled:
            t0 = time.perf_counter()
            twists, known = self.keyframe_twists(mc)
            if known[kid]:
                try:
                    polished = motion_polish(src, dst, T_keyframe_query, twists[kid], mc, query_twist)
                except (ArithmeticError, ValueError, np.linalg.LinAlgError) as exc:  # a numerical failure: rigid pose
                    _log.warning("motion compensation failed on keyframe %d (%s); rigid pose kept", kid, exc)
            result.timings_ms["motion_ms"] = (time.perf_counter() - t0) * 1e3
            if polished is not None:
                T_keyframe_query = polished.T_dst_src
        T_map_keyframe = np.asarray(best.T_map_keyframe, np.float64)
        covariance = None
        if cc.enabled:
            t0 = time.perf_counter()
            if polished is not None:  # the covariance is of the pose as fitted: both sweeps de-skewed as the fit did
                src, dst = deskewed(src, polished.twist, mc), deskewed(dst, twists[kid], mc)
            try:
                in_keyframe = registration_covariance(src, dst, T_keyframe_query, cc,
                                                      motion_compensated=polished is not None)
            except (ArithmeticError, ValueError, np.linalg.LinAlgError) as exc:  # a numerical failure: none
                _log.warning("pose covariance failed on keyframe %d (%s); none given", kid, exc)
                in_keyframe = None
            if in_keyframe is not None:
                covariance = rotate_covariance(in_keyframe, float(T_map_keyframe[2]))
            result.timings_ms["covariance_ms"] = (time.perf_counter() - t0) * 1e3
        if polished is None:
            return replace(result, pose_covariance=covariance, motion_compensated=False)
        old = best
        best = replace(best, T_keyframe_query=polished.T_dst_src)
        # the winner's entry among the candidates answers the same pose (the API lists both)
        candidates = [best if c is old else c for c in result.candidates]
        return replace(result, best=best, candidates=candidates, pose_covariance=covariance, motion_compensated=True,
                       T_map_query=compose(T_map_keyframe, polished.T_dst_src))

    def _candidate(self, keyframe_id: int, rank: int = 0, descriptor_distance: float = 0.0,
                   wrap: Callable[..., Any] | None = None) -> Candidate:
        """A ``Candidate`` of keyframe ``keyframe_id`` whose features, screen data and landmark grid come from the
        cache on first use (through ``wrap(fetch, keyframe_id)`` when given: the read-stage timer)."""
        def direct(fetch: Callable[[int], Any], j: int) -> Callable[[], Any]:
            return lambda: fetch(j)

        wrap = wrap or direct
        return Candidate(int(keyframe_id), np.asarray(self.keyframes.poses[keyframe_id], np.float64).copy(), None,
                         float(descriptor_distance), int(rank), loader=wrap(self.cache.get, keyframe_id),
                         grid_loader=wrap(self.cache.landmark_grid, keyframe_id))

    def place_repetition(self, keyframe_id: int, config: LocalizationConfig | None = None) -> PlaceRepetition:
        """How well the map shows keyframe ``keyframe_id``'s place elsewhere (``localization.repetition``): localized
        like a query against its ``config.repetition_neighbours`` nearest keyframes within
        ``config.place_margin_radius_m`` and the ``config.repetition_rivals`` keyframes retrieved for its global
        descriptor that lie farther. Computed on first use (~25 screens and 1 + ``repetition_verify`` pose
        estimates, ~20-40 ms) and cached per keyframe and settings; deterministic, so concurrent queries that
        compute it twice store the same answer."""
        config = config or self.config
        settings = repetition_key(config)
        key = (int(keyframe_id), settings)
        with self._cache_lock:
            table = self._repetition_tables.get(settings)
            known = self._repetition.get(key) if table is None else table.at(int(keyframe_id))
        if known is not None:
            return known
        kid = int(keyframe_id)
        poses = self.keyframes.poses
        # same-place keyframes (a dense map, several drives) can fill the retrieval: search past them
        within = int((distances_from(kid, poses) <= config.place_margin_radius_m).sum())
        idx, _ = self.index.search(np.asarray(self.index.vector(kid), np.float32).reshape(-1),
                                   min(config.repetition_rivals + within, len(self)))
        neighbours, rivals = repetition_keyframes(kid, poses, [int(i) for i in idx[0] if i >= 0],
                                                  config.place_margin_radius_m, config.repetition_neighbours)
        rivals = rivals[: config.repetition_rivals]
        rep = place_repetition(self.cache.get(kid).features, np.asarray(poses[kid], np.float64),
                               [self._candidate(j) for j in neighbours], [self._candidate(j) for j in rivals], config)
        with self._cache_lock:
            self._repetition[key] = rep
        return rep

    def place_repetitions(self, config: LocalizationConfig | None = None, workers: int | None = None,
                          progress: Callable[[int, int], None] | None = None) -> RepetitionTable:
        """Every keyframe's ``place_repetition`` under ``config`` (default: the localizer's), as one table: what
        ``reradar build-map`` stores in a map, so that no query pays the 20-40 ms of measuring its winner's.

        Args:
            workers: threads measuring keyframes at once (the compiled kernels release the GIL; default
                ``default_repetition_workers``: the usable cores, at most 4); the table is the same for any number
                (each keyframe's measure is deterministic).
            progress: called with (done, total) as keyframes are measured.

        Returns:
            ``RepetitionTable`` (row i = keyframe i); the repetitions are also cached in this localizer.
        """
        config = config or self.config
        workers = default_repetition_workers() if workers is None else workers
        if workers < 1:
            raise ConfigError(f"workers must be >= 1, got {workers}")
        n = len(self)
        out: list[PlaceRepetition | None] = [None] * n

        def measure(keyframe_id: int) -> None:
            out[keyframe_id] = self.place_repetition(keyframe_id, config)

        pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="place-repetition") if workers > 1 else None
        try:
            for done, _ in enumerate(pool.map(measure, range(n)) if pool else map(measure, range(n)), start=1):
                if progress is not None:
                    progress(done, n)
        finally:  # a progress callback that raises (a cancelled build) stops the keyframes not yet begun
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
        rows = [r for r in out if r is not None]
        assert len(rows) == n, "every keyframe is measured before the table is made"
        return RepetitionTable.of(repetition_settings(config), rows)

    def adopt_repetitions(self, table: RepetitionTable, config: LocalizationConfig | None = None) -> bool:
        """Use ``table`` (measured beforehand, e.g. stored in the map) for ``config``'s repeated-place check when it
        was measured under the same settings (``repetition_settings``) on a map of this size; returns whether it
        was taken. A table of other settings is left out: the check then measures keyframes as they win."""
        config = config or self.config
        if len(table) != len(self) or table.settings != repetition_settings(config):
            return False
        with self._cache_lock:
            self._repetition_tables[repetition_key(config)] = table
        return True

    def track(self, features: ScanFeatures, prior: PosePrior,
              config: LocalizationConfig | None = None) -> LocalizationResult:
        """Tracking mode (``localization.tracking``): register the scan to the keyframes nearest to ``prior``;
        when no answer passes the aligned-landmark bar, the prior's gate, the reversal and turn checks
        (``_reversal_fits_as_well``, ``_turn_fits_as_well``) and the confidence bar (``config.effective_min_confidence``), fall back to
        ``localize``. A prior looser than the registration reaches, in position or heading
        (``TrackingConfig.covers``), is not tracked from: the scan is localized globally (``mode="global"``,
        ``tracking_lost`` False).

        Returns:
            ``mode="tracking"`` when tracking succeeded, else the global answer with ``tracking_lost=True``;
            ``timings_ms["track_ms"]`` is the tracking attempt either way.
        """
        self._check_features(features, "Localizer.track")
        config = self._call_config(config)
        tcfg = config.tracking
        if not tcfg.covers(prior):
            return self.localize(features, config)
        g = np.asarray(features.global_descriptor, np.float32).reshape(-1)
        if g.shape[0] != self.index.dim:  # as ``retrieve``: the descriptor distance is a confidence cue
            raise ConfigError(f"query descriptor has {g.shape[0]} values but the map stores {self.index.dim}")
        t0 = time.perf_counter()
        ids = tracking_candidates(self.keyframes.poses, prior, tcfg)
        radii = tcfg.radii(prior)
        n = int(features.keypoints_xy_m.shape[0])
        verified: list[CandidateVerification] = []
        accepted: list[tuple[CandidateVerification, np.ndarray]] = []
        for rank, kid in enumerate(ids):
            T_map_kf = np.asarray(self.keyframes.poses[kid], np.float64)
            reg = register_from_prior(features, self.cache.landmark_grid(int(kid)),
                                      relative_to_keyframe(T_map_kf, prior), radii)
            T_map_query = compose(T_map_kf, reg.T_keyframe_query)
            bar = reg.num_inliers >= config.min_inliers and reg.inlier_ratio >= config.effective_min_inlier_ratio
            consistent = within_gate(T_map_query, prior, tcfg)
            dist = float(np.linalg.norm(self.index.vector(int(kid)) - g))
            v = CandidateVerification(
                keyframe_id=int(kid), rank=rank, descriptor_distance=dist,
                timestamp_us=int(self.keyframes.timestamps_us[kid]), T_map_keyframe=T_map_kf, num_matches=n,
                num_inliers=reg.num_inliers, inlier_ratio=reg.inlier_ratio,
                T_keyframe_query=reg.T_keyframe_query if bar and consistent else None,
                reason=None if bar and consistent else (REASON_INCONSISTENT if bar else REASON_TOO_FEW_INLIERS),
                inlier_spread_m=reg.inlier_spread_m)
            verified.append(v)
            if v.T_keyframe_query is not None:
                accepted.append((v, T_map_query))
        answer = max(accepted, key=lambda a: (a[0].num_inliers, -a[0].rank)) if accepted else None
        if answer is not None and (self._reversal_fits_as_well(features, answer[0], radii, config)
                                   or self._turn_fits_as_well(features, answer[0], answer[1], prior, config)):
            answer = None  # the prior's heading is contradicted, or undecidable: localize globally
        if answer is not None:
            best, T_map_query = answer
            # the global answers' model and bar, on the cues a registration from a prior measures (the competition
            # cues it never looks at at the model's means: ``tracked_cues``): a tracked answer the model doubts is
            # localized globally instead, like a failed registration
            model = default_confidence_model()
            cues = confidence_cues(best, verified, model.place_radius_m, model.top_n)
            if cues is not None:
                cues = tracked_cues(cues, model)
            confidence = float(model.predict(cues)) if cues is not None else 0.0
            if config.pose_method != "guided" or confidence >= config.effective_min_confidence:  # as ``localize``
                track_ms = (time.perf_counter() - t0) * 1e3
                return self._final_pose(
                    features, LocalizationResult("localized", None, best, T_map_query, verified,
                                                 {"track_ms": track_ms, "verify_ms": track_ms}, confidence, cues,
                                                 mode="tracking"), config, prior.twist)
        track_ms = (time.perf_counter() - t0) * 1e3
        result = self.localize(features, config)
        result.tracking_lost = True
        result.timings_ms["track_ms"] = track_ms
        return result

    def _reversal_fits_as_well(self, features: ScanFeatures, best: CandidateVerification,
                               radii: tuple[float, ...], config: LocalizationConfig) -> bool:
        """Whether the tracked answer, turned by 180 degrees about the sensor and registered again, aligns as many
        of the query's landmarks (within ``min_place_margin`` of them). A street that looks alike both ways fits
        a prior turned by 180 degrees as well as the true one, and the prior's gate accepts what lies near the
        prior: a prior 180 degrees off with a heading sigma of 2 degrees was tracked to the reversed heading at
        confidence 0.99999 (QA, session 22). On ``loop-sim`` (157 revisits, prior at the truth) the reversal of a
        right answer aligned 29-76 % of the query's landmarks fewer, that of a reversed answer 35-45 % more."""
        assert best.T_keyframe_query is not None
        turned = register_from_prior(features, self.cache.landmark_grid(best.keyframe_id),
                                     compose(best.T_keyframe_query, np.array([0.0, 0.0, np.pi])), radii)
        margin = config.margin_landmarks(int(features.keypoints_xy_m.shape[0]))
        return turned.num_inliers >= best.num_inliers - margin

    def _turn_fits_as_well(self, features: ScanFeatures, best: CandidateVerification, T_map_query: np.ndarray,
                           prior: PosePrior, config: LocalizationConfig) -> bool:
        """Whether the tracked answer, turned about the sensor to a heading outside the prior's heading gate and
        more than ``AlignmentConfig.ambiguity_separation_rad`` (10 degrees) from its own (within
        ``TrackingConfig.turn_check_rad``, every ``turn_check_step_rad``), aligns as many of the query's
        landmarks (scored like the pose hypotheses, within ``min_place_margin`` of them). The registration starts
        at the prior's heading and settles in the nearest basin, and the gate then accepts it: a prior 15-25
        degrees off with a heading sigma of 2 degrees was tracked 11-19 degrees off at confidence 0.85-0.99 (1 of
        157 ``loop-sim`` revisits each). Those answers turned by 11-21 degrees aligned 1.3-1.6 times their own
        count, while no right answer's best turn outside the gate reached 0.82 of its own (157 + 156 revisits,
        prior 0 and 5 degrees off; docs/BENCHMARKS.md, "Session 24")."""
        assert best.T_keyframe_query is not None
        tcfg = config.tracking
        n_steps = int(tcfg.turn_check_rad // tcfg.turn_check_step_rad)
        turns = np.arange(-n_steps, n_steps + 1) * tcfg.turn_check_step_rad
        # a rival is a heading the prior excludes and another basin than the answer's (the pose estimator's
        # separation of rival poses): turns of a degree or two score about as the answer itself
        outside = ((np.abs(wrap_angle(float(T_map_query[2]) + turns - float(prior.T_map_query[2])))
                    > tcfg.yaw_gate_rad(prior)) & (np.abs(turns) > config.alignment.ambiguity_separation_rad))
        if not outside.any():
            return False
        x, y, yaw = (float(v) for v in best.T_keyframe_query)
        poses = np.column_stack([np.full(len(turns), x), np.full(len(turns), y), yaw + turns])  # turned about the sensor
        counts = count_aligned(poses, features.keypoints_xy_m, self.cache.landmark_grid(best.keyframe_id),
                               config.alignment.score_threshold_m)
        own = int(counts[n_steps])
        margin = config.margin_landmarks(int(features.keypoints_xy_m.shape[0]))
        return int(counts[outside].max()) >= own - margin

    def clear(self) -> None:
        """Drop the cached keyframes (the place repetitions, a few bytes each, stay)."""
        self.cache.clear()
