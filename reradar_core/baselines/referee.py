"""ReFeree: free-space place descriptor (retrieval) plus an azimuth free-space descriptor (initial heading).

References:
    B. Choi, H. Kim and Y. Cho, "ReFeree: Radar-based efficient global descriptor using a Feature and Free
    space for Place Recognition", ICRA 2024 workshop; H. Kim, B. Choi, E. Choi and Y. Cho, "ReFeree:
    Radar-Based Lightweight and Robust Localization Using Feature and Free space", RA-L 2024.
    Reference implementation: github.com/sparolab/referee, the released Python version at commit
    09dae25915e8ad6132877f30b5cb839b70f23109: ``python/utils/feature_extractor.py`` (``cen2018features``,
    ``targets_to_polar_image``), ``python/utils/referee.py`` (``generate_r_referee``, ``generate_a_referee``),
    ``python/test.py`` (KD-tree retrieval); the journal evaluation code at commit
    d81ed6030120d89cee92df04cf3ce9f035b7cbb2 (``util/params.py``: 8 azimuth rows per sector, 50 sectors on
    400-azimuth scans; ``util/recognition/referee.py``: ``cKDTree`` nearest neighbour); the heading search of
    ``cpp/src/referee.cpp`` (``ReFereeA::maxScoreIdx``, ``getYawDiff``) at commit
    d50dcf0aeedc14fa78d31f472a504418d2b0550d (the Python test's shift loop never shifts).

Pipeline (``referee``):
    1. features, the authors' Python Cen 2018 detector on the (A, R) polar power: q = power - row mean;
       p = box filter of 17 bins along range (``uniform_filter1d``, mode ``reflect``); sigma_q from the
       negative part of q (sqrt of mean q^2 over q < 0); y = q (1 - N(q - p)) + p (N(q - p) - N(p)) with
       N(x) = exp(-x^2 / (2 sigma_q^2)); every run of consecutive bins with y > 3 sigma_q gives one feature
       at the run's middle bin (``run[len // 2]``), kept when that bin is > 58;
    2. binary polar image of the features;
    3. ReFeree-R: per range bin the number of azimuths without a feature, summed over ``R // 80`` nearly
       equal chunks (``np.array_split``) -> raw counts; retrieval = Euclidean nearest neighbour on them;
    4. ReFeree-A: ``A // 8`` sectors of 8 azimuth rows; per sector the free bins in front of each ray's
       farthest feature (zeros in ``row[:last]``), divided by 8 * R; heading = the circular sector shift
       with the highest cosine similarity, times 360 / number of sectors.

ReFeree estimates no translation, so the paper (Sec. Evaluation Metrics) counts a success as a correct
retrieval with rotation error below 10 degrees.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from reradar_core.baselines.base import PlaceRecognitionMethod, Prepared
from reradar_core.io.scan import RadarScan

__all__ = ["ReFereeConfig", "ReFeree", "referee_features", "feature_image", "r_referee", "a_referee"]


@dataclass(frozen=True)
class ReFereeConfig:
    """Reference settings: detector (box 17 bins, z_q 3, minimum range 58 bins), 80-bin range chunks,
    8 azimuth rows per heading sector."""

    box_bins: int = 17
    z_q: float = 3.0
    min_range_bins: int = 58
    range_window_bins: int = 80
    rows_per_sector: int = 8


def referee_features(power: np.ndarray, min_range: int = 58, zq: float = 3.0,
                     box: int = 17) -> tuple[np.ndarray, np.ndarray]:
    """The authors' Python Cen 2018 detector: (A, R) polar power -> (azimuth rows, range bins) int64 arrays.

    Scale-invariant (power in [0, 1] or bytes give the same features). Rows without any negative q (a
    constant row) have no noise estimate and give no features.
    """
    x = np.asarray(power, dtype=np.float64)
    q = x - x.mean(axis=1, keepdims=True)
    p = ndimage.uniform_filter1d(q, size=box, axis=1, mode="reflect")
    neg = q < 0
    count = neg.sum(axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        sigma = np.sqrt(np.where(neg, q * q, 0.0).sum(axis=1, keepdims=True) / count)
        nqp = np.exp(-0.5 * ((q - p) / sigma) ** 2)
        npp = np.exp(-0.5 * (p / sigma) ** 2)
        y = q * (1.0 - nqp) + p * (nqp - npp)
        mask = y > zq * sigma  # NaN sigma (no noise estimate) -> False
    # runs of consecutive above-threshold bins per row: starts and (exclusive) ends from the padded diff
    pad = np.zeros((mask.shape[0], 1), dtype=np.int8)
    d = np.diff(np.concatenate([pad, mask.astype(np.int8), pad], axis=1), axis=1)
    s_rows, s_bins = np.nonzero(d == 1)
    _, e_bins = np.nonzero(d == -1)  # row-major order: the k-th end closes the k-th start
    mid = s_bins + (e_bins - s_bins) // 2
    keep = mid > min_range
    return s_rows[keep].astype(np.int64), mid[keep].astype(np.int64)


def feature_image(power: np.ndarray, config: ReFereeConfig = ReFereeConfig()) -> np.ndarray:
    """(A, R) bool polar image: True at every feature of ``referee_features``."""
    rows, bins = referee_features(power, config.min_range_bins, config.z_q, config.box_bins)
    img = np.zeros(np.asarray(power).shape, dtype=bool)
    img[rows, bins] = True
    return img


def r_referee(img: np.ndarray, window: int = 80) -> np.ndarray:
    """(A, R) bool feature image -> (max(R // window, 1),) float64 free-azimuth counts per range chunk."""
    free = np.count_nonzero(~img, axis=0)
    n = max(img.shape[1] // window, 1)
    return np.array([c.sum() for c in np.array_split(free, n)], dtype=np.float64)


def a_referee(img: np.ndarray, rows_per_sector: int = 8) -> np.ndarray:
    """(A, R) bool feature image -> (max(A // rows_per_sector, 1),) float64 sector free-space ratios."""
    n_az, n_bins = img.shape
    has = img.any(axis=1)
    last = np.where(has, n_bins - 1 - np.argmax(img[:, ::-1], axis=1), 0)
    before = np.cumsum(img, axis=1)  # features at or before each bin
    feats_before_last = np.where(has, before[np.arange(n_az), last] - 1, 0)
    zeros = (last - feats_before_last).astype(np.float64)  # zeros in row[:last]
    cells = np.array_split(np.arange(n_az), max(n_az // rows_per_sector, 1))
    total = cells[0].size * n_bins
    return np.array([zeros[c].sum() for c in cells], dtype=np.float64) / total


class ReFeree(PlaceRecognitionMethod):
    """ReFeree-R retrieval (Euclidean on raw free-space counts) + ReFeree-A heading (sector shift)."""

    name = "referee"
    provides_heading = True
    algorithm_version = 3

    def __init__(self, config: ReFereeConfig = ReFereeConfig()) -> None:
        self.config = config

    def params(self) -> dict[str, Any]:
        c = self.config
        return {"box": c.box_bins, "z_q": c.z_q, "min_range": c.min_range_bins, "window": c.range_window_bins,
                "rows": c.rows_per_sector}

    def prepare(self, scan: RadarScan) -> Prepared:
        img = feature_image(scan.power, self.config)
        return {"ring": r_referee(img, self.config.range_window_bins),
                "sectors": a_referee(img, self.config.rows_per_sector)}

    def describe_prepared(self, prepared: Prepared) -> np.ndarray:
        """[n_ring, ReFeree-R (n_ring raw counts), ReFeree-A]: one flat float64 vector; the leading count
        says where the heading part starts."""
        ring = np.asarray(prepared["ring"], dtype=np.float64)
        return np.concatenate([[ring.size], ring, np.asarray(prepared["sectors"], dtype=np.float64)])

    @staticmethod
    def _split(desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = int(desc[0])
        return desc[1 : 1 + n], desc[1 + n :]

    def build_index(self, db_descs: Any) -> Any:
        descs = [np.asarray(d, dtype=np.float64) for d in db_descs]
        # float64 differences, not the |a|^2 - 2ab + |b|^2 expansion: raw counts are ~1e4 per chunk and
        # neighbouring places differ by a few counts, which float32 expansion would round away
        return {"ring": np.stack([self._split(d)[0] for d in descs]),
                "sectors": np.stack([self._split(d)[1] for d in descs])}

    def distance(self, q_desc: np.ndarray, index: Any) -> np.ndarray:
        ring, _ = self._split(np.asarray(q_desc, dtype=np.float64))
        return np.sqrt(((index["ring"] - ring[None]) ** 2).sum(axis=1))

    def estimate_heading(self, q_desc: np.ndarray, index: Any, j: int) -> float | None:
        _, q = self._split(np.asarray(q_desc, np.float64))
        d = np.asarray(index["sectors"][j], np.float64)
        norm = float(np.linalg.norm(q) * np.linalg.norm(d))
        if norm == 0.0:
            return 0.0
        # score[s] = sum_j q[j + s] d[j] (C++ maxScoreIdx); a CCW yaw of +theta moves azimuths by +theta
        score = np.array([np.dot(np.roll(q, -s), d) for s in range(q.size)]) / norm
        s = int(np.argmax(score))
        return float(np.mod(s * 2.0 * np.pi / q.size + np.pi, 2.0 * np.pi) - np.pi)
