"""Planar geometry: SE(2) poses and the polar -> Cartesian radar image transform."""

from reradar_core.geometry.cartesian import (
    CartesianConfig,
    metric_to_pixel,
    pixel_to_metric,
    polar_to_cartesian,
    polar_to_metric,
)
from reradar_core.geometry.se2 import (
    angle_diff,
    compose,
    inverse,
    matrix_to_se2,
    relative_pose,
    se2_to_matrix,
    transform_points,
    wrap_angle,
)

__all__ = [
    "CartesianConfig",
    "angle_diff",
    "compose",
    "inverse",
    "matrix_to_se2",
    "metric_to_pixel",
    "pixel_to_metric",
    "polar_to_cartesian",
    "polar_to_metric",
    "relative_pose",
    "se2_to_matrix",
    "transform_points",
    "wrap_angle",
]
