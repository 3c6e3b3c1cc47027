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
    "check_poses",
    "check_yaw_radians",
]


def check_poses(poses: object, what: str = "poses") -> np.ndarray:
    """``poses`` as an (N, 3) float64 array of (x metres, y metres, yaw radians) (one (3,) pose as (1, 3)), or
    ``ConfigError`` saying why not: another shape (e.g. (N, 2) positions, which a reshape would interleave into wrong
    poses), non-finite values, or a position beyond ``MAX_ABS_COORDINATE_M``."""
    from reradar_core.bounds import MAX_ABS_COORDINATE_M
    from reradar_core.errors import ConfigError

    try:
        arr = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{what} must be an (N, 3) array of x, y (metres) and yaw (radians): {exc}") from None
    if arr.shape == (3,):
        arr = arr.reshape(1, 3)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ConfigError(f"{what} must be an (N, 3) array of x, y (metres) and yaw (radians), got shape {arr.shape}")
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        raise ConfigError(f"{what}: {int(bad.sum())} pose(s) hold NaN or infinite values (first: row "
                          f"{int(np.flatnonzero(bad)[0])})")
    if np.any(np.abs(arr[:, :2]) > MAX_ABS_COORDINATE_M):
        raise ConfigError(f"{what}: positions must lie within +-{MAX_ABS_COORDINATE_M:.0e} m of the origin")
    return arr


def check_yaw_radians(poses: np.ndarray, what: str = "poses", min_steps: int = 5) -> None:
    """``ConfigError`` when the headings of a drive's (N, 3) ``poses`` read as degrees and not radians. Only headings
    with some |yaw| beyond 2 pi are judged, over the moves of 0.5 m or more (fewer than ``min_steps``: no verdict):

    - on a drive that turns, the heading keeps a steady angle to the direction of travel (the sensor's mounting)
      when read as degrees (steadiness above 0.9, 1 = constant) and clearly less so (by 0.1) when read as radians;
    - on a drive whose headings span less than one turn (a straight road, where both readings keep a constant
      angle), read as degrees the heading lies along the direction of travel (within 10 degrees, either way round)
      and read as radians it does not (more than 20 degrees off): e.g. a drive north at "90".

    Unwrapped radian headings (beyond 2 pi after a loop) follow the travel as radians and pass."""
    from reradar_core.errors import ConfigError

    p = np.asarray(poses, np.float64)
    if len(p) < 2 or not np.any(np.abs(p[:, 2]) > 2 * np.pi + 1e-6) or np.any(np.abs(p[:, 2]) > 360.0 + 1e-6):
        return
    d = np.diff(p[:, :2], axis=0)
    moving = np.hypot(d[:, 0], d[:, 1]) >= 0.5
    if int(moving.sum()) < min_steps:
        return
    travel = np.arctan2(d[moving, 1], d[moving, 0])
    yaw = p[:-1, 2][moving]
    top = np.max(np.abs(p[:, 2]))
    if np.ptp(p[:, 2]) < 2 * np.pi:
        def off_axis_deg(heading: np.ndarray) -> float:  # median angle to the line of travel (a reversal folded)
            return float(np.degrees(np.median(np.abs(wrap_angle(2.0 * (heading - travel)))) / 2.0))

        as_radians, as_degrees = off_axis_deg(yaw), off_axis_deg(np.radians(yaw))
        if as_degrees < 10.0 and as_radians > 20.0:
            raise ConfigError(f"{what}: the headings look like degrees (up to {top:.1f}; read as degrees they lie "
                              f"{as_degrees:.1f} degrees off the direction of travel, as radians {as_radians:.1f}); "
                              "give yaw in radians (numpy.radians)")
        return

    def steadiness(heading: np.ndarray) -> float:  # 1: a constant angle between heading and travel
        return float(np.abs(np.mean(np.exp(1j * (heading - travel)))))

    as_radians_s, as_degrees_s = steadiness(yaw), steadiness(np.radians(yaw))
    if as_degrees_s > 0.9 and as_degrees_s > as_radians_s + 0.1:
        raise ConfigError(f"{what}: the headings look like degrees (up to {top:.1f}; read as "
                          f"degrees they follow the direction of travel steadily, {as_degrees_s:.2f} against "
                          f"{as_radians_s:.2f} as radians); give yaw in radians (numpy.radians)")


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


def _pose_array(T: np.ndarray, name: str) -> np.ndarray:
    """``T`` as float64 (..., 3) poses, or ``ValueError`` naming it ((N, 2) positions failed as an IndexError)."""
    a = np.asarray(T, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(f"{name} must be (..., 3) poses (x m, y m, yaw rad), got shape {a.shape}")
    return a


def compose(T_a_b: np.ndarray, T_b_c: np.ndarray) -> np.ndarray:
    """T_a_c = T_a_b * T_b_c for (..., 3) poses."""
    a = _pose_array(T_a_b, "T_a_b")
    b = _pose_array(T_b_c, "T_b_c")
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def inverse(T_a_b: np.ndarray) -> np.ndarray:
    """T_b_a from T_a_b for (..., 3) poses."""
    p = _pose_array(T_a_b, "T_a_b")
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
    if p.shape != (3,):
        raise ValueError(f"T_a_b must be a single (3,) pose (x m, y m, yaw rad), got shape {p.shape}")
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points_b must be (N, 2) x, y in metres, got shape {pts.shape}")
    c, s = np.cos(p[2]), np.sin(p[2])
    R = np.array([[c, -s], [s, c]])
    return pts @ R.T + p[:2]
