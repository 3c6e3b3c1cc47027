"""ResNet18-NetVLAD: the OORD benchmark's neural baseline.

References:
    M. Gadd et al., "OORD: The Oxford Offroad Radar Dataset", IEEE T-ITS 2024: an ImageNet-pretrained
    ResNet-18 on the 128 x 128 polar radar image, NetVLAD with 64 clusters whose centres are initialised by
    k-means++ on deep features of the reference run; the backbone is not fine-tuned on radar (as the ReRadar
    paper, Sec. Implementation Details, repeats).
    R. Arandjelovic et al., "NetVLAD: CNN architecture for weakly supervised place recognition", CVPR 2016
    (soft assignment, alpha from the centre-similarity gap, intra-normalisation, L2).

Offline substitute (stated in docs/BENCHMARKS.md): ImageNet weights cannot be downloaded on this machine, so
the backbone is ResNet-18 with torchvision's random initialisation under a fixed seed (``seed``); only the
NetVLAD centres are fit on the reference run, exactly as in OORD. A checkpoint with ImageNet weights in
this module's parameter names can be given as ``weights_path``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from reradar_core.baselines.base import EuclideanIndex, PlaceRecognitionMethod, Prepared, polar_resize
from reradar_core.baselines.kmeans import kmeans
from reradar_core.baselines.resnet18 import ResNet18
from reradar_core.errors import ConfigError
from reradar_core.io.scan import RadarScan

__all__ = ["ResNetNetVLADConfig", "ResNetNetVLAD", "netvlad_numpy"]

_IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
_IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)


@dataclass(frozen=True)
class ResNetNetVLADConfig:
    """OORD settings: 128 x 128 polar input, 64 NetVLAD clusters (k-means++ on the reference run)."""

    input_px: int = 128
    num_clusters: int = 64
    seed: int = 0
    weights_path: str | None = None
    kmeans_iterations: int = 20


def netvlad_numpy(features: np.ndarray, centres: np.ndarray, alpha: float) -> np.ndarray:
    """NetVLAD of (M, C) L2-normalised local features with (K, C) unit centres -> (K*C,) float32.

    Soft assignment softmax_k(alpha * (2 c_k.x - |c_k|^2)) (Arandjelovic et al. initialisation), residual
    sums, intra-normalisation, then L2.
    """
    x = np.asarray(features, dtype=np.float64)
    c = np.asarray(centres, dtype=np.float64)
    logits = alpha * (2.0 * x @ c.T - (c * c).sum(1)[None])
    logits -= logits.max(axis=1, keepdims=True)
    a = np.exp(logits)
    a /= a.sum(axis=1, keepdims=True)  # (M, K)
    v = a.T @ x - a.sum(0)[:, None] * c  # (K, C)
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    v = v.reshape(-1)
    return (v / max(float(np.linalg.norm(v)), 1e-12)).astype(np.float32)


class ResNetNetVLAD(PlaceRecognitionMethod):
    """ResNet-18 conv5 features on the polar image + NetVLAD (centres from the database); cosine distance."""

    name = "resnet18-netvlad"
    needs_fit = True

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
        return {"px": c.input_px, "seed": c.seed, "weights": c.weights_path, "v": 1}

    @torch.no_grad()
    def prepare(self, scan: RadarScan) -> Prepared:
        img = polar_resize(scan.power, self.config.input_px, self.config.input_px)
        x = (img[None] - _IMAGENET_MEAN[:, None, None]) / _IMAGENET_STD[:, None, None]  # grey -> 3 channels
        fmap = self.net.forward_features(torch.from_numpy(x[None].astype(np.float32)))[0]
        local = torch.nn.functional.normalize(fmap.flatten(1).T, dim=1)  # (M, 512) unit rows
        return {"local": local.numpy().astype(np.float32)}

    def fit(self, database: Sequence[Prepared]) -> None:
        if not database:
            raise ConfigError("ResNet18-NetVLAD needs a non-empty reference run to fit its NetVLAD centres")
        feats = np.concatenate([np.asarray(p["local"], dtype=np.float32) for p in database])
        k = min(self.config.num_clusters, feats.shape[0])
        c = kmeans(feats, k, self.config.kmeans_iterations, self.config.seed)
        c /= np.maximum(np.linalg.norm(c, axis=1, keepdims=True), 1e-12)
        # alpha as in the NetVLAD reference code: -log(0.01) / mean gap between the two closest centres
        sample = feats[np.random.default_rng(self.config.seed).choice(feats.shape[0], min(5000, feats.shape[0]),
                                                                      replace=False)]
        dots = np.sort(sample @ c.T, axis=1)[:, ::-1]
        gap = float(np.mean(dots[:, 0] - dots[:, 1])) if k > 1 else 1.0
        self.alpha = float(-np.log(0.01) / max(gap, 1e-6))
        self.centres = c

    def describe_prepared(self, prepared: Prepared) -> np.ndarray:
        if self.centres is None:
            raise ConfigError("ResNetNetVLAD.fit(database) must run before describing scans")
        return netvlad_numpy(prepared["local"], self.centres, self.alpha)

    def build_index(self, db_descs: Any) -> Any:
        return EuclideanIndex(db_descs)

    def distance(self, q_desc: np.ndarray, index: Any) -> np.ndarray:
        return index.distances(q_desc)
