"""Per-scan features: the boundary between the descriptor model and retrieval / pose estimation / maps."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ScanFeatures"]


@dataclass
class ScanFeatures:
    """Everything retrieval and pose verification need from one scan.

    Attributes:
        global_descriptor: (D,) float32, L2-normalised; nearest neighbour by inner product.
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
        self.keypoints_xy_m = np.asarray(self.keypoints_xy_m, dtype=np.float32).reshape(-1, 2)
        self.local_descriptors = np.asarray(self.local_descriptors, dtype=np.float16)
        if self.local_descriptors.ndim != 2 or self.local_descriptors.shape[0] != self.keypoints_xy_m.shape[0]:
            raise ValueError(
                f"local descriptors {self.local_descriptors.shape} do not match "
                f"{self.keypoints_xy_m.shape[0]} keypoints"
            )
