"""(Open-)RadVLAD: |FFT| along each polar beam aggregated with hard-assignment VLAD.

References:
    M. Gadd and P. Newman, "Open-RadVLAD: Fast and Robust Radar Place Recognition", IEEE RadarConf 2024.
    Reference implementation: OORD benchmark code, github.com/mttgdd/oord-dataset at commit
    f04683fb68d15f042395de528c92064dbfc4bc30: ``config/radvlad.yaml`` (min_bin 60, max_bin 3768, polar,
    num_azis = num_bins = 256, fft, num_clusters 64), ``src/dataset.py`` (``load_image``), ``src/radvlad.py``
    (``do_cluster``, ``get_vlad``), ``jobs/test_radvlad.py``, ``src/compute_distance_matrix.py`` (Euclidean).

``radvlad`` (the reference):
    1. bins < 60 zeroed, bins >= 3768 cut (``reradar_core.baselines.oord``);
    2. polar image resized to 256 azimuths x 256 bins (Pillow bicubic);
    3. every azimuth (beam) -> ``|np.fft.fft(beam)|``, all 256 bins (the mirrored upper half included);
    4. 64-word vocabulary: k-means++ and Lloyd to convergence on every beam of the reference run
       (``kmeans_to_convergence``, scikit-learn's ``KMeans(tol=1e-4, n_init=1)`` semantics);
    5. VLAD with hard assignment: residual sums per word, flattened, signed square root, L2;
    6. Euclidean distance.

``radvlad-half`` is the variant this project ran before (kept for comparison, not the reference): no range
cut-off, ``cv2.INTER_AREA`` resize, the lower 128 |FFT| bins, 20 FAISS Lloyd iterations on at most 50,000
beams.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from reradar_core.baselines.base import EuclideanIndex, PlaceRecognitionMethod, Prepared, polar_resize
from reradar_core.baselines.kmeans import kmeans, kmeans_to_convergence
from reradar_core.baselines.oord import MAX_BIN, MIN_BIN, oord_polar_image
from reradar_core.errors import ConfigError
from reradar_core.io.scan import RadarScan

__all__ = ["RadVLADConfig", "RadVLAD", "RadVLADHalf", "beam_fft_features", "beam_fft_features_half", "vlad"]


@dataclass(frozen=True)
class RadVLADConfig:
    """OORD ``config/radvlad.yaml``: 256 x 256 polar image, range bins [60, 3768), 64 clusters.

    ``kmeans_tol`` / ``kmeans_max_iter``: scikit-learn's defaults, which the reference uses.
    """

    num_azimuths: int = 256
    num_range: int = 256
    min_bin: int = MIN_BIN
    max_bin: int = MAX_BIN
    num_clusters: int = 64
    kmeans_tol: float = 1e-4
    kmeans_max_iter: int = 300
    seed: int = 0


def beam_fft_features(power: np.ndarray, config: RadVLADConfig = RadVLADConfig()) -> np.ndarray:
    """(A, R) polar power in [0, 1] -> (num_azimuths, num_range) float32 |FFT| of every resized beam."""
    small = oord_polar_image(power, config.num_azimuths, config.num_range, config.min_bin, config.max_bin)
    return np.abs(np.fft.fft(small, axis=1)).astype(np.float32)


def beam_fft_features_half(power: np.ndarray, num_azimuths: int = 256, num_range: int = 256) -> np.ndarray:
    """The earlier variant: area resize, no cut-off, lower ``num_range // 2`` |FFT| bins (float32)."""
    small = polar_resize(power, num_azimuths, num_range)
    return np.abs(np.fft.rfft(small, axis=1))[:, : num_range // 2].astype(np.float32)


def vlad(features: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Hard-assignment VLAD: (M, D) local features, (K, D) centres -> (K*D,) float32 (signed sqrt, L2).

    Residuals are summed in float64 as the reference (``np.zeros`` accumulator); a feature goes to its
    nearest centre (Euclidean), ties to the lower index.
    """
    f = np.asarray(features, dtype=np.float64)
    c = np.asarray(centres, dtype=np.float64)
    d2 = (f * f).sum(1)[:, None] - 2.0 * f @ c.T + (c * c).sum(1)[None]
    assign = np.argmin(d2, axis=1)
    k, d = c.shape
    v = np.zeros((k, d), dtype=np.float64)
    np.add.at(v, assign, f - c[assign])
    flat = (np.sign(v) * np.sqrt(np.abs(v))).reshape(-1)
    return (flat / max(float(np.linalg.norm(flat)), 1e-12)).astype(np.float32)


class RadVLAD(PlaceRecognitionMethod):
    """Beam-|FFT| + VLAD with a vocabulary fit on the database (OORD reference); Euclidean; no heading."""

    name = "radvlad"
    needs_fit = True
    algorithm_version = 2

    def __init__(self, config: RadVLADConfig = RadVLADConfig()) -> None:
        self.config = config
        self.centres: np.ndarray | None = None

    def params(self) -> dict[str, Any]:
        c = self.config
        return {"az": c.num_azimuths, "range": c.num_range, "min_bin": c.min_bin, "max_bin": c.max_bin}

    def prepare(self, scan: RadarScan) -> Prepared:
        return {"beams": beam_fft_features(scan.power, self.config)}

    def _vocabulary(self, feats: np.ndarray) -> np.ndarray:
        c = self.config
        return kmeans_to_convergence(feats, c.num_clusters, c.seed, c.kmeans_tol, c.kmeans_max_iter)

    def fit(self, database: Sequence[Prepared]) -> None:
        if not database:
            raise ConfigError(f"{self.name} needs a non-empty reference run to fit its vocabulary")
        feats = np.concatenate([np.asarray(p["beams"], dtype=np.float32) for p in database])
        self.centres = self._vocabulary(feats)

    def describe_prepared(self, prepared: Prepared) -> np.ndarray:
        if self.centres is None:
            raise ConfigError(f"{self.name}: fit(database) must run before describing scans")
        return vlad(prepared["beams"], self.centres)

    def build_index(self, db_descs: Any) -> Any:
        return EuclideanIndex(db_descs)

    def distance(self, q_desc: np.ndarray, index: Any) -> np.ndarray:
        return index.distances(q_desc)


class RadVLADHalf(RadVLAD):
    """The variant this project ran before the reference was followed (see the module docstring)."""

    name = "radvlad-half"
    algorithm_version = 1
    kmeans_iterations = 20

    def params(self) -> dict[str, Any]:
        c = self.config
        return {"az": c.num_azimuths, "range": c.num_range}

    def prepare(self, scan: RadarScan) -> Prepared:
        return {"beams": beam_fft_features_half(scan.power, self.config.num_azimuths, self.config.num_range)}

    def _vocabulary(self, feats: np.ndarray) -> np.ndarray:
        return kmeans(feats, self.config.num_clusters, self.kmeans_iterations, self.config.seed)
