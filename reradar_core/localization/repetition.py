"""Place repetition: whether another place of the map looks like a keyframe's own place.

A street built of one repeated block (a row of identical houses, a periodic world of the simulator) shows the
radar the same scene every period. A scan there fits the map at every period; which keyframe wins is chance,
and the tie margin (``LocalizationConfig.min_place_margin``) does not see it when the keyframe that wins sits at
the scan's position within the period and the true place's keyframes sit a few metres off it: the winner then
out-screens them by 8-11 % of the landmarks (QA, session 26: 2 of 20 answers one or two periods off on a road
along a tile border, 40-80 m off at confidence 0.96-0.99). That is a property of the map, not of the scan, so
it is measured on the map: a keyframe is localized against the map's other keyframes as a query would be. Its
best aligned ratio against a keyframe of its own place (a neighbour a few metres away) is what a scan there
aligns; a keyframe farther than the place radius whose own best pose puts the keyframe *at another place*
(not the same place seen from 20-60 m away, which any keyframe down the road shows), aligns at least what an
answer must (the aligned-ratio floor: below it a reversed or slid pose is the noise every street shows, QA
session 27) and about as much as the neighbour means the place repeats, and an answer resting on it is an unknown
place (``ambiguous``), never a guess.

    rep = place_repetition(features, T_map_keyframe, neighbours, rivals, config)
    rep.ratio   # rival / neighbour aligned ratio; >= LocalizationConfig.max_place_repetition (0.95) -> refused

``Localizer.place_repetition`` chooses the keyframes and caches the answer per keyframe;
``Localizer.place_repetitions`` measures every keyframe once into a ``RepetitionTable``, which a map stores (written
by ``reradar build-map``, docs/MAP_FORMAT.md) so that no query pays for it, and ``Localizer.adopt_repetitions`` takes
one back when it was measured under the settings in use (``repetition_settings``).
"""

from __future__ import annotations

import dataclasses
import json
import os
import typing
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.se2 import compose
from reradar_core.localization.pipeline import Candidate, LocalizationConfig, verify_candidate
from reradar_core.localization.screening import screen_candidates

__all__ = ["PlaceRepetition", "REPETITION_SETTINGS", "REPETITION_SETTINGS_VERSION", "RepetitionTable",
           "default_repetition_workers", "distances_from", "place_repetition", "repetition_key",
           "repetition_keyframes", "repetition_settings"]


@dataclass(frozen=True)
class PlaceRepetition:
    """How well the map shows one keyframe's place elsewhere.

    Attributes:
        neighbour_score: the aligned ratio (fraction of the keyframe's landmarks its pose estimate aligns, in
            [0, 1]) against the best-screened keyframe of its own place; 0 when it has none (or no pose).
        rival_score: the best aligned ratio against a keyframe of another place whose pose puts the keyframe
            farther than the place radius from where it is, among those that reach the answers' aligned-ratio floor
            (``LocalizationConfig.effective_min_inlier_ratio``); 0 when there is none.
        rival_keyframe_id: that keyframe (None when there is none).
    """

    neighbour_score: float
    rival_score: float
    rival_keyframe_id: int | None

    @property
    def ratio(self) -> float:
        """``rival_score / neighbour_score``: about 1 where the place repeats, 0 on most streets (no keyframe
        elsewhere poses it elsewhere); 0 when the keyframe has no neighbour at its place (not judged)."""
        return self.rival_score / self.neighbour_score if self.neighbour_score > 0.0 else 0.0


#: The settings of ``LocalizationConfig`` that ``Localizer.place_repetition`` and ``place_repetition`` read (the
#: choice of keyframes, the screen, the pose estimate and the floor), by name (``effective_min_inlier_ratio`` is a
#: property); ``alignment`` and ``ransac`` are dataclasses of settings.
REPETITION_SETTINGS = ("place_margin_radius_m", "repetition_rivals", "repetition_neighbours", "repetition_verify",
                       "pose_method", "min_inliers", "match_ratio", "effective_min_inlier_ratio", "alignment", "ransac")
#: Version of ``repetition_settings``' layout: a table stored under another is measured again.
REPETITION_SETTINGS_VERSION = 1


def repetition_key(config: LocalizationConfig) -> tuple:
    """``REPETITION_SETTINGS`` of ``config`` as a tuple: a cached repetition is reused only under the same key."""
    return tuple(getattr(config, name) for name in REPETITION_SETTINGS)


def default_repetition_workers() -> int:
    """Threads for measuring a whole map's place repetition (``Localizer.place_repetitions``): the cores this
    process may use, at most 4 (2 threads measure 1.7x as fast as 1 on 2 cores: the kernels release the GIL)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    return max(1, min(4, cores))


def _plain(value: Any) -> Any:
    """``value`` as JSON-ready plain data: dataclasses as dicts of their fields, tuples as lists, numpy scalars as
    Python numbers; a field declared ``float`` as a float even when given as an int (20 and 20.0 are one setting,
    as in ``repetition_key``'s tuple equality)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        hints = typing.get_type_hints(type(value))
        return {f.name: _plain(_as_declared(getattr(value, f.name), hints.get(f.name))) for f in dataclasses.fields(value)}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _as_declared(value: Any, hint: Any) -> Any:
    """An int ``value`` of a field whose declared type admits float but not int, as a float."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        admits = typing.get_args(hint) or (hint,)
        if float in admits and int not in admits:
            return float(value)
    return value


def repetition_settings(config: LocalizationConfig) -> str:
    """``REPETITION_SETTINGS`` of ``config`` as canonical JSON (an object by name, sorted keys, with the layout's
    ``version``): stored with a ``RepetitionTable`` (in a map file), so a table is used only under the settings it
    was measured with."""
    hints = typing.get_type_hints(type(config))
    named: dict[str, Any] = {"version": REPETITION_SETTINGS_VERSION}
    for name in REPETITION_SETTINGS:
        value = getattr(config, name)
        named[name] = _plain(float(value) if name == "effective_min_inlier_ratio"
                             else _as_declared(value, hints.get(name)))
    return json.dumps(named, sort_keys=True, separators=(",", ":"))


@dataclass(frozen=True, eq=False)
class RepetitionTable:
    """Every keyframe's ``PlaceRepetition`` of one map, measured under one setting (``Localizer.place_repetitions``).

    Attributes:
        settings: ``repetition_settings`` of the configuration it was measured with.
        neighbour_score, rival_score: (N,) float64 aligned ratios in [0, 1] (``PlaceRepetition``), row i = keyframe i.
        rival_keyframe_id: (N,) int64, the rival keyframe, -1 where there is none.

    Raises:
        ConfigError: arrays of other shapes or lengths, scores outside [0, 1] or not finite, rival ids outside
            [-1, N), a keyframe its own rival, or a rival id without a score (or a score without one).
    """

    settings: str
    neighbour_score: np.ndarray
    rival_score: np.ndarray
    rival_keyframe_id: np.ndarray

    def __post_init__(self) -> None:
        neighbour = np.asarray(self.neighbour_score, np.float64)
        rival = np.asarray(self.rival_score, np.float64)
        ids = np.asarray(self.rival_keyframe_id)
        if neighbour.ndim != 1 or rival.shape != neighbour.shape or ids.shape != neighbour.shape:
            raise ConfigError(f"place repetition arrays must be three (N,) arrays of one length, got shapes "
                              f"{neighbour.shape}, {rival.shape}, {ids.shape}")
        if ids.dtype.kind not in "iu":
            raise ConfigError(f"rival keyframe ids must be integers, got {ids.dtype}")
        if ids.dtype.kind == "u" and ids.size and int(ids.max()) > np.iinfo(np.int64).max:
            raise ConfigError("rival keyframe ids must fit in int64")  # a uint64 would wrap to -1 on the cast
        ids = ids.astype(np.int64)
        n = neighbour.shape[0]
        for name, a in (("neighbour", neighbour), ("rival", rival)):
            if not (np.all(np.isfinite(a)) and np.all((a >= 0.0) & (a <= 1.0))):
                raise ConfigError(f"{name} scores of a place repetition table must lie in [0, 1]")
        if np.any((ids < -1) | (ids >= n)) or np.any(ids == np.arange(n)):
            raise ConfigError(f"rival keyframe ids must lie in [-1, {n}) and differ from their own keyframe")
        if np.any((ids >= 0) != (rival > 0.0)):
            raise ConfigError("a rival keyframe id needs a rival score above 0, and a rival score a keyframe id")
        for name, a in (("neighbour_score", neighbour), ("rival_score", rival), ("rival_keyframe_id", ids)):
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    def __len__(self) -> int:
        return int(self.neighbour_score.shape[0])

    def at(self, keyframe_id: int) -> PlaceRepetition:
        """Keyframe ``keyframe_id``'s ``PlaceRepetition``."""
        rid = int(self.rival_keyframe_id[keyframe_id])
        return PlaceRepetition(float(self.neighbour_score[keyframe_id]), float(self.rival_score[keyframe_id]),
                               None if rid < 0 else rid)

    @property
    def ratios(self) -> np.ndarray:
        """(N,) float64 ``PlaceRepetition.ratio`` of every keyframe."""
        n = self.neighbour_score
        return np.divide(self.rival_score, n, out=np.zeros_like(n), where=n > 0.0)

    @property
    def max_ratio(self) -> float:
        """The largest repetition of the map (0 for an empty one)."""
        return float(self.ratios.max(initial=0.0))

    def marked(self, bar: float | None) -> int:
        """Keyframes whose repetition reaches ``bar`` (``LocalizationConfig.max_place_repetition``; None: none)."""
        return 0 if bar is None else int((self.ratios >= bar).sum())

    @property
    def unjudged(self) -> int:
        """Keyframes the check cannot judge: no keyframe of their own place (within the place radius) aligned with
        them (``neighbour_score`` 0), e.g. on a map whose keyframes lie farther apart than the radius."""
        return int((self.neighbour_score <= 0.0).sum())

    @classmethod
    def of(cls, settings: str, repetitions: Sequence[PlaceRepetition]) -> RepetitionTable:
        """The table of ``repetitions`` (item i = keyframe i)."""
        return cls(settings, np.array([r.neighbour_score for r in repetitions], np.float64),
                   np.array([r.rival_score for r in repetitions], np.float64),
                   np.array([-1 if r.rival_keyframe_id is None else r.rival_keyframe_id for r in repetitions],
                            np.int64))


def distances_from(keyframe_id: int, poses: np.ndarray) -> np.ndarray:
    """(N,) float64 distances (metres, map frame) from keyframe ``keyframe_id`` to every keyframe of (N, 3) ``poses``."""
    xy = np.asarray(poses, np.float64)[:, :2]
    return np.hypot(*(xy - xy[keyframe_id]).T)


def repetition_keyframes(keyframe_id: int, poses: np.ndarray, retrieved: Sequence[int], radius_m: float,
                         max_neighbours: int) -> tuple[list[int], list[int]]:
    """The keyframes ``place_repetition`` compares a keyframe with.

    Args:
        keyframe_id: the keyframe.
        poses: (N, 3) map poses of all keyframes (x m, y m, yaw rad; map frame).
        retrieved: keyframe ids retrieved for it by global descriptor (best first; itself may be among them).
        radius_m: the place radius: a keyframe within it (position) is the same place.
        max_neighbours: same-place keyframes kept, the nearest first (a map that drives a street several times
            holds many).

    Returns:
        (neighbours, rivals): the nearest ``max_neighbours`` other keyframes within ``radius_m``, and the
        retrieved keyframes farther than ``radius_m``, in retrieval order.
    """
    dist = distances_from(keyframe_id, poses)
    near = np.flatnonzero(dist <= radius_m)
    near = near[near != keyframe_id]
    neighbours = [int(j) for j in near[np.argsort(dist[near], kind="stable")][:max_neighbours]]
    rivals = [int(j) for j in retrieved if j != keyframe_id and dist[int(j)] > radius_m]
    return neighbours, rivals


def place_repetition(features: ScanFeatures, T_map_keyframe: np.ndarray, neighbours: Sequence[Candidate],
                     rivals: Sequence[Candidate], config: LocalizationConfig) -> PlaceRepetition:
    """Localize one keyframe against keyframes of its own place and of other places (``repetition_keyframes``).

    All are screened (``screen_candidates``); the best-screened neighbour and the ``config.repetition_verify``
    best-screened rivals are verified (``verify_candidate``: the query's pose estimate). A rival counts when its
    pose puts the keyframe farther than ``config.place_margin_radius_m`` from ``T_map_keyframe`` and aligns at least
    the answers' floor (``config.effective_min_inlier_ratio``).

    Args:
        features: the keyframe's features (landmarks in metres, its sensor frame; unit local descriptors).
        T_map_keyframe: (3,) its map pose (x m, y m, yaw rad).
        neighbours, rivals: ``Candidate`` s of the other keyframes (map poses, features or loaders).
        config: the query's settings (screen, pose estimate, place radius, ``repetition_verify``).

    Returns:
        ``PlaceRepetition`` (deterministic: the screen and the estimator are seeded).
    """
    def best_screened(cands: Sequence[Candidate], k: int) -> list[Candidate]:
        if not cands:
            return []
        scores = screen_candidates(features.keypoints_xy_m, features.local_descriptors,
                                   [c.screen_data(config.alignment) for c in cands], config.alignment)
        return [cands[int(i)] for i in np.argsort(-scores, kind="stable")[:k]]

    here = np.asarray(T_map_keyframe, np.float64)
    neighbour = 0.0
    for c in best_screened(neighbours, 1):
        v = verify_candidate(features, c, config)
        neighbour = v.inlier_ratio if v.T_keyframe_query is not None else 0.0
    rival, rival_id = 0.0, None
    floor = config.effective_min_inlier_ratio
    for c in best_screened(rivals, config.repetition_verify):
        v = verify_candidate(features, c, config)
        # a rival is a place the scan could be answered at: below the answers' floor it is the noise of wrong
        # poses (reversed, slid along the street: 0.23-0.43 on ordinary streets 12-20 m between keyframes, QA)
        if v.T_keyframe_query is None or v.inlier_ratio < floor or v.inlier_ratio <= rival:
            continue
        posed = compose(np.asarray(c.T_map_keyframe, np.float64), v.T_keyframe_query)
        if float(np.hypot(*(posed[:2] - here[:2]))) > config.place_margin_radius_m:  # not this place from afar
            rival, rival_id = float(v.inlier_ratio), int(c.keyframe_id)
    return PlaceRepetition(float(neighbour), rival, rival_id)
