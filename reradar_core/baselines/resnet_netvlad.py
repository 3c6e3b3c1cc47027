"""ResNet18-NetVLAD: the OORD benchmark's neural baseline.

References:
    M. Gadd et al., "OORD: The Oxford Offroad Radar Dataset", IEEE T-ITS 2024; R. Arandjelovic et al.,
    "NetVLAD: CNN architecture for weakly supervised place recognition", CVPR 2016.
    Reference implementation: OORD benchmark code, github.com/mttgdd/oord-dataset at commit
    f04683fb68d15f042395de528c92064dbfc4bc30: ``config/resnet18_netvlad.yaml`` (min_bin 60, max_bin 3768,
    polar, num_azis = num_bins = 128, channels 3), ``src/dataset.py`` (``load_image``,
    ``prepare_output_tensor``), ``src/resnet18_netvlad.py`` (``NetVLAD``, ``Net``),
    ``jobs/test_resnet18_netvlad.py`` (``calib``), ``src/compute_distance_matrix.py`` (Euclidean ``cdist``).

``resnet18-netvlad`` follows the reference step by step, its quirks included (they shape the published
numbers):
    1. bins < 60 zeroed; polar image resized (Pillow bicubic) to 128 x 128; power in [0, 1] repeated into 3
       channels, *without* ImageNet mean/std normalisation;
    2. ResNet-18 up to conv5 (``layer4``): (512, 4, 4) -> 16 local descriptors of 512 channels;
    3. calibration on the reference run: each scan's (16, 512) feature matrix is L2-normalised *over the 16
       positions* per channel (the reference normalises ``dim=1`` after the permute), then
       ``KMeans(64, k-means++, tol 1e-4, n_init 1)`` on all of them (``kmeans_to_convergence``); the
       centres are used as they come (not unit-normalised);
    4. alpha = -ln(0.01) / mean(i_2^2 - i_1^2) where i_1, i_2 are the *indices* of each centre's two
       nearest calibration descriptors (the reference takes ``kneighbors(...)[1]``, the index array, where
       the NetVLAD paper means the squared distances); for realistic run lengths alpha is tiny and the
       soft assignment nearly uniform;
    5. NetVLAD forward: descriptors L2-normalised over channels; soft assignment softmax_k(2 alpha c_k.x -
       alpha |c_k|) (the bias uses the norm, not its square); residual sums; intra-normalisation; L2;
    6. Euclidean distance.

Offline substitute (stated in docs/BENCHMARKS.md): ImageNet weights cannot be downloaded on this machine, so
the backbone is ResNet-18 with torchvision's random initialisation under a fixed seed (``seed``); a
checkpoint with ImageNet weights in this module's parameter names can be given as ``weights_path``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from reradar_core.baselines.base import EuclideanIndex, PlaceRecognitionMethod, Prepared
from reradar_core.baselines.kmeans import kmeans_to_convergence
from reradar_core.baselines.oord import MAX_BIN, MIN_BIN, oord_polar_image
from reradar_core.baselines.resnet18 import ResNet18
from reradar_core.errors import ConfigError
from reradar_core.io.scan import RadarScan

__all__ = ["ResNetNetVLADConfig", "ResNetNetVLAD", "netvlad_numpy", "reference_alpha", "normalise_positions"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class ResNetNetVLADConfig:
    """OORD settings: 128 x 128 polar input, bins [60, 3768), 64 NetVLAD clusters (k-means on the reference
    run, to convergence). ``seed``: backbone initialisation; ``kmeans_seed``: the centres' k-means."""

    input_px: int = 128
    min_bin: int = MIN_BIN
    max_bin: int = MAX_BIN
    num_clusters: int = 64
    seed: int = 0
    weights_path: str | None = None
    kmeans_seed: int = 0
    kmeans_tol: float = 1e-4
    kmeans_max_iter: int = 300


def normalise_positions(local: np.ndarray) -> np.ndarray:
    """(M, C) local descriptors of one scan -> each channel L2-normalised over the M positions (float32).

    What the reference's calibration does (``F.normalize(..., dim=1)`` on a (B, M, C) tensor)."""
    x = np.asarray(local, dtype=np.float32)
    return x / np.maximum(np.linalg.norm(x, axis=0, keepdims=True), 1e-12)


def reference_alpha(centres: np.ndarray, train: np.ndarray) -> float:
    """The reference's alpha: -ln(0.01) / mean(i_2^2 - i_1^2), i_1 / i_2 = *indices* (into ``train``) of the
    two nearest training descriptors of each centre (exact Euclidean search)."""
    import faiss

    index = faiss.IndexFlatL2(train.shape[1])
    index.add(np.ascontiguousarray(train, dtype=np.float32))
    _, idx = index.search(np.ascontiguousarray(centres, dtype=np.float32), 2)
    ds_sq = np.square(idx.astype(np.float64))
    gap = float(np.mean(ds_sq[:, 1] - ds_sq[:, 0]))
    if gap == 0.0:  # cannot happen with distinct indices unless every centre has the same neighbours
        raise ConfigError("ResNet18-NetVLAD calibration is degenerate (no index gap); use a longer reference run")
    return float(-np.log(0.01) / gap)


def netvlad_numpy(features: np.ndarray, centres: np.ndarray, alpha: float) -> np.ndarray:
    """The reference NetVLAD layer on one scan: (M, C) local features, (K, C) centres -> (K*C,) float32.

    Features are L2-normalised over channels; soft assignment softmax_k(2 alpha c_k.x - alpha |c_k|);
    residual sums; intra-normalisation; L2.
    """
    x = np.asarray(features, dtype=np.float64)
    x = x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)
    c = np.asarray(centres, dtype=np.float64)
    logits = 2.0 * alpha * x @ c.T - alpha * np.linalg.norm(c, axis=1)[None]
    logits -= logits.max(axis=1, keepdims=True)
    a = np.exp(logits)
    a /= a.sum(axis=1, keepdims=True)  # (M, K)
    v = a.T @ x - a.sum(0)[:, None] * c  # (K, C)
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    v = v.reshape(-1)
    return (v / max(float(np.linalg.norm(v)), 1e-12)).astype(np.float32)


class ResNetNetVLAD(PlaceRecognitionMethod):
    """ResNet-18 conv5 features on the polar image + NetVLAD calibrated on the database; Euclidean."""

    name = "resnet18-netvlad"
    needs_fit = True
    algorithm_version = 2

    def min_database_scans(self) -> int:
        """More database descriptors than NetVLAD centres: ``num_clusters`` (64) centres are fitted by k-means on
        one descriptor per cell of the ResNet-18 conv5 map ((input_px / 32)^2 = 16 per scan at 128 px); with no
        more descriptors than centres every centre is a descriptor itself and the reference's alpha (from the
        indices of each centre's two nearest descriptors, ``reference_alpha``) is 0/0 whenever the nearest
        neighbours pair up: 38 of 38 two-scan and 1 of 37 three-scan windows of a simulated Boreas drive, none
        from 4 scans on. So 5 scans at the OORD settings."""
        per_scan = math.ceil(self.config.input_px / 32) ** 2
        return self.config.num_clusters // per_scan + 1

    def __init__(self, config: ResNetNetVLADConfig = ResNetNetVLADConfig()) -> None:
        self.config = config
        gen_state = torch.random.get_rng_state()
        torch.manual_seed(config.seed)
        self.net = ResNet18(3)
        torch.random.set_rng_state(gen_state)
        if config.weights_path:
            path = Path(config.weights_path)
            if not path.is_file():
                raise ConfigError(f"ResNet-18 weights {path} not found; omit weights_path for the seeded init")
            self.net.load_state_dict(torch.load(path, map_location="cpu", weights_only=True), strict=False)
        self.net.eval()
        self.centres: np.ndarray | None = None
        self.alpha: float = 0.0

    def params(self) -> dict[str, Any]:
        c = self.config
        return {"px": c.input_px, "min_bin": c.min_bin, "max_bin": c.max_bin, "seed": c.seed,
                "weights": c.weights_path}

    @torch.no_grad()
    def prepare(self, scan: RadarScan) -> Prepared:
        c = self.config
        img = oord_polar_image(scan.power, c.input_px, c.input_px, c.min_bin, c.max_bin)
        x = torch.from_numpy(np.repeat(img[None, None], 3, axis=1).astype(np.float32))  # grey -> 3 channels
        fmap = self.net.forward_features(x)[0]  # (512, H', W')
        return {"local": fmap.flatten(1).T.contiguous().numpy().astype(np.float32)}  # (M, 512), raw

    def fit(self, database: Sequence[Prepared]) -> None:
        if not database:
            raise ConfigError("ResNet18-NetVLAD needs a non-empty reference run to fit its NetVLAD centres")
        feats = np.concatenate([normalise_positions(p["local"]) for p in database])
        k = min(self.config.num_clusters, feats.shape[0])
        self.centres = kmeans_to_convergence(feats, k, self.config.kmeans_seed, self.config.kmeans_tol,
                                             self.config.kmeans_max_iter)
        self.alpha = reference_alpha(self.centres, feats)
        logger.info("resnet18-netvlad: alpha %.3g from %d calibration descriptors", self.alpha, feats.shape[0])

    def describe_prepared(self, prepared: Prepared) -> np.ndarray:
        if self.centres is None:
            raise ConfigError("ResNetNetVLAD.fit(database) must run before describing scans")
        return netvlad_numpy(prepared["local"], self.centres, self.alpha)

    def build_index(self, db_descs: Any) -> Any:
        return EuclideanIndex(db_descs)

    def distance(self, q_desc: np.ndarray, index: Any) -> np.ndarray:
        return index.distances(q_desc)
