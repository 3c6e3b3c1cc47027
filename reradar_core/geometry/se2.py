"""SE(2) helpers on (x, y, yaw) arrays.

A pose ``T_a_b = (x, y, yaw)`` maps a point p_b in frame b to frame a: p_a = R(yaw) p_b + (x, y).
Angles are radians, counter-clockwise positive; arrays may carry leading batch dimensions (..., 3).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "wrap_angle",
    "angle_diff",
    "se2_to_matrix",
    "matrix_to_se2",
    "compose",
    "inverse",
    "relative_pose",
    "transform_points",
]


def wrap_angle(angle: np.ndarray | float) -> np.ndarray:
    """Wrap radians to (-pi, pi]."""
    a = np.asarray(angle, dtype=np.float64)
    w = np.mod(a + np.pi, 2.0 * np.pi) - np.pi
    return np.where(w == -np.pi, np.pi, w)


def angle_diff(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    """Absolute angular difference |a - b| on the circle, radians in [0, pi]."""
    return np.abs(wrap_angle(np.asarray(a) - np.asarray(b)))


def se2_to_matrix(pose: np.ndarray) -> np.ndarray:
    """(..., 3) (x, y, yaw) -> (..., 3, 3) homogeneous matrices."""
    p = np.asarray(pose, dtype=np.float64)
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    m = np.zeros(p.shape[:-1] + (3, 3))
    m[..., 0, 0], m[..., 0, 1], m[..., 0, 2] = c, -s, p[..., 0]
    m[..., 1, 0], m[..., 1, 1], m[..., 1, 2] = s, c, p[..., 1]
    m[..., 2, 2] = 1.0
    return m


def matrix_to_se2(m: np.ndarray) -> np.ndarray:
    """(..., 3, 3) homogeneous matrices -> (..., 3) (x, y, yaw)."""
    m = np.asarray(m, dtype=np.float64)
    return np.stack([m[..., 0, 2], m[..., 1, 2], np.arctan2(m[..., 1, 0], m[..., 0, 0])], axis=-1)


def compose(T_a_b: np.ndarray, T_b_c: np.ndarray) -> np.ndarray:
    """T_a_c = T_a_b * T_b_c for (..., 3) poses."""
    a = np.asarray(T_a_b, dtype=np.float64)
    b = np.asarray(T_b_c, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def inverse(T_a_b: np.ndarray) -> np.ndarray:
    """T_b_a from T_a_b for (..., 3) poses."""
    p = np.asarray(T_a_b, dtype=np.float64)
    c, s = np.cos(p[..., 2]), np.sin(p[..., 2])
    x = -(c * p[..., 0] + s * p[..., 1])
    y = -(-s * p[..., 0] + c * p[..., 1])
    return np.stack([x, y, wrap_angle(-p[..., 2])], axis=-1)


def relative_pose(T_w_a: np.ndarray, T_w_b: np.ndarray) -> np.ndarray:
    """T_a_b = inverse(T_w_a) * T_w_b: pose of b expressed in a's frame."""
    return compose(inverse(T_w_a), T_w_b)


def transform_points(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Map (N, 2) points from frame b to frame a with a single (3,) pose."""
    p = np.asarray(T_a_b, dtype=np.float64)
    pts = np.asarray(points_b, dtype=np.float64)
    c, s = np.cos(p[2]), np.sin(p[2])
    R = np.array([[c, -s], [s, c]])
    return pts @ R.T + p[:2]
