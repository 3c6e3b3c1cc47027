"""Local descriptor matching and robust 2-D rigid pose estimation (RANSAC)."""

from reradar_core.matching.alignment import (
    AlignmentConfig,
    LandmarkGrid,
    build_landmark_grid,
    count_aligned,
    estimate_pose_guided,
    refine_pose,
    screen_alignment,
)
from reradar_core.matching.descriptors import cosine_similarity, match_descriptors
from reradar_core.matching.ransac import RansacConfig, RigidEstimate, estimate_rigid_2d, fit_rigid_2d

__all__ = [
    "AlignmentConfig",
    "LandmarkGrid",
    "build_landmark_grid",
    "count_aligned",
    "estimate_pose_guided",
    "refine_pose",
    "screen_alignment",
    "RansacConfig",
    "RigidEstimate",
    "cosine_similarity",
    "estimate_rigid_2d",
    "fit_rigid_2d",
    "match_descriptors",
]
