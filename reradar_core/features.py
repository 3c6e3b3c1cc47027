"""Per-scan features: the boundary between the descriptor model and retrieval / pose estimation / maps."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ScanFeatures"]

#: How far a global descriptor's norm may stray from 1 (a float16 store rounds it by ~1e-3).
_UNIT_NORM_SLACK = 1e-2


@dataclass
class ScanFeatures:
    """Everything retrieval and pose verification need from one scan.

    Attributes:
        global_descriptor: (D,) float32, L2-normalised (one of another norm is normalised here; zero or
            non-finite is a ValueError); nearest neighbour by inner product.
        keypoints_xy_m: (N, 2) float32 landmark positions in the scan's sensor frame, metres
            (x forward, y left), from the Cen 2018 detector.
        local_descriptors: (N, C) float16, L2-normalised rows, read from F' at each keypoint.
        timestamp_us: scan timestamp (first azimuth), microseconds.
    """

    global_descriptor: np.ndarray
    keypoints_xy_m: np.ndarray
    local_descriptors: np.ndarray
    timestamp_us: int = 0

    def __post_init__(self) -> None:
        self.global_descriptor = np.asarray(self.global_descriptor, dtype=np.float32).reshape(-1)
        norm = float(np.linalg.norm(self.global_descriptor))
        if not (np.isfinite(norm) and norm > 0):
            raise ValueError(f"global_descriptor must be a finite, non-zero vector, got norm {norm:.4g}")
        if abs(norm - 1.0) > _UNIT_NORM_SLACK:
            # retrieval scores inner products and the confidence reads descriptor distances: a scaled descriptor
            # was answered with a confidence it had not earned (QA); one already of unit norm is kept bit for bit
            self.global_descriptor = self.global_descriptor / np.float32(norm)
        xy = np.asarray(self.keypoints_xy_m, dtype=np.float32)
        if xy.size == 0:
            xy = xy.reshape(0, 2)
        if xy.ndim != 2 or xy.shape[1] != 2:  # (2, N) reshaped to (N, 2) would interleave into other points
            raise ValueError(f"keypoints_xy_m must be (N, 2) sensor-frame x, y in metres, got shape {xy.shape}")
        self.keypoints_xy_m = xy
        self.local_descriptors = np.asarray(self.local_descriptors, dtype=np.float16)
        if self.local_descriptors.ndim != 2 or self.local_descriptors.shape[0] != self.keypoints_xy_m.shape[0]:
            raise ValueError(
                f"local descriptors {self.local_descriptors.shape} do not match "
                f"{self.keypoints_xy_m.shape[0]} keypoints"
            )
