"""Dense registration (``matching.dense``): known poses between scans rendered from one set of reflectors."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.errors import ConfigError
from reradar_core.geometry.cartesian import CartesianConfig
from reradar_core.geometry.se2 import inverse, transform_points
from reradar_core.io.scan import RadarScan
from reradar_core.matching.dense import DenseConfig, dense_image, register_dense, register_dense_best

FAR = CartesianConfig(257, 1.28)  # the far view's geometry
RANGE_RES_M = 0.25
N_AZ, N_BINS = 400, 700  # 175 m of range


def render(points_world: np.ndarray, T_world_sensor: np.ndarray, seed: int) -> RadarScan:
    """A polar scan of point reflectors (one azimuth x ~1 m blobs) seen from ``T_world_sensor``, with speckle."""
    rng = np.random.default_rng(seed)
    xy = transform_points(inverse(T_world_sensor), points_world)
    rng_m = np.hypot(xy[:, 0], xy[:, 1])
    az = np.mod(np.arctan2(-xy[:, 1], xy[:, 0]), 2 * np.pi)  # clockwise from +x (polar_to_metric)
    power = rng.uniform(0.0, 0.08, size=(N_AZ, N_BINS)).astype(np.float32)
    bins = np.arange(N_BINS) * RANGE_RES_M
    for r, a in zip(rng_m, az, strict=True):
        row = int(round(a / (2 * np.pi) * N_AZ)) % N_AZ
        blob = 0.8 * np.exp(-0.5 * ((bins - r) / 0.6) ** 2)
        for d, w in ((-1, 0.5), (0, 1.0), (1, 0.5)):
            power[(row + d) % N_AZ] = np.maximum(power[(row + d) % N_AZ], w * blob)
    return RadarScan(np.clip(power, 0, 1), np.arange(N_AZ) * 2 * np.pi / N_AZ,
                     np.arange(N_AZ, dtype=np.int64) * 625, RANGE_RES_M, 0.0)


@pytest.fixture(scope="module")
def reflectors() -> np.ndarray:
    rng = np.random.default_rng(0)
    r = rng.uniform(30.0, 160.0, size=90)
    a = rng.uniform(0, 2 * np.pi, size=90)
    return np.column_stack([r * np.cos(a), r * np.sin(a)])


@pytest.mark.parametrize("T_kf_query", [(4.0, -3.0, np.deg2rad(20.0)), (-9.0, 6.5, np.deg2rad(-137.0)),
                                         (0.0, 0.0, np.deg2rad(180.0))])
def test_recovers_a_known_pose_at_any_heading(reflectors, T_kf_query) -> None:
    T = np.array(T_kf_query)
    kf = dense_image(render(reflectors, np.zeros(3), seed=1), FAR)
    q = dense_image(render(reflectors, T, seed=2), FAR)
    reg = register_dense(q, kf, FAR)
    np.testing.assert_allclose(reg.T_keyframe_query[:2], T[:2], atol=0.5)
    err = np.rad2deg(np.angle(np.exp(1j * (reg.T_keyframe_query[2] - T[2]))))
    assert abs(err) < 0.5
    assert reg.heading_margin > 0.2 and reg.score > reg.heading_margin
    assert reg.shift_margin > 0.5 and not reg.at_edge  # scattered reflectors fix the translation uniquely


@pytest.mark.parametrize("spacing_m", [3.0, 20.0])
def test_a_scene_that_repeats_along_itself_leaves_the_translation_open(spacing_m) -> None:
    """A straight bank (returns every 3 m) or a row of posts (every 20 m) 70 m to the side: it aligns at one heading
    only, but as well one step along itself (QA session 39: accepted 10-52 m off on the heading margin alone)."""
    xs = np.arange(-400.0, 400.0, spacing_m)
    posts = np.column_stack([xs, np.full_like(xs, 70.0)])
    kf = dense_image(render(posts, np.zeros(3), seed=1), FAR)
    for k, dx in enumerate((-9.0, 5.0)):
        reg = register_dense(dense_image(render(posts, np.array([dx, 1.0, 0.05]), seed=2 + k), FAR), kf, FAR)
        assert reg.shift_margin < 0.25


def test_a_shift_beyond_the_search_window_is_flagged(reflectors) -> None:
    kf = dense_image(render(reflectors, np.zeros(3), seed=1), FAR)
    q = dense_image(render(reflectors, np.array([0.0, -34.0, np.deg2rad(30.0)]), seed=2), FAR)
    assert register_dense(q, kf, FAR).at_edge  # the window reaches +-30.72 m


def test_an_empty_scene_aligns_about_as_well_at_every_heading(reflectors) -> None:
    """Speckle alone: no heading stands out, so the margin stays far below the far view's bar (0.05)."""
    kf = dense_image(render(reflectors[:0], np.zeros(3), seed=3), FAR)
    q = dense_image(render(reflectors[:0], np.zeros(3), seed=4), FAR)
    assert register_dense(q, kf, FAR).heading_margin < 0.02


def test_best_of_several_keyframes_is_the_one_that_saw_the_place(reflectors) -> None:
    rng = np.random.default_rng(5)
    others = [rng.uniform(-150, 150, size=(90, 2)) for _ in range(3)]
    T = np.array([2.0, 1.0, np.deg2rad(45.0)])
    q = dense_image(render(reflectors, T, seed=6), FAR)
    kfs = [dense_image(render(o, np.zeros(3), seed=7 + i), FAR) for i, o in enumerate(others)]
    kfs.insert(2, dense_image(render(reflectors, np.zeros(3), seed=10), FAR))
    win, reg = register_dense_best(q, kfs, FAR)
    assert win == 2
    np.testing.assert_allclose(reg.T_keyframe_query[:2], T[:2], atol=0.5)


def test_dense_image_is_zero_mean_inside_the_disc_and_zero_outside(reflectors) -> None:
    img = dense_image(render(reflectors, np.zeros(3), seed=1), FAR)
    assert img.shape == (257, 257) and img.dtype == np.float32
    assert img[0, 0] == 0.0 and img[0, -1] == 0.0
    c = 128
    yy, xx = np.mgrid[:257, :257]
    assert abs(float(img[np.hypot(yy - c, xx - c) <= c].mean())) < 1e-5


def test_bad_inputs_are_refused() -> None:
    ok = np.zeros((257, 257), np.float32)
    with pytest.raises(ValueError, match=r"\(257, 257\)"):
        register_dense(np.zeros((201, 201)), ok, FAR)
    bad = ok.copy()
    bad[3, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        register_dense(ok, bad, FAR)
    with pytest.raises(ValueError, match="at least one"):
        register_dense_best(ok, [], FAR)
    with pytest.raises(ValueError, match="RadarScan"):
        dense_image(np.zeros((400, 700)), FAR)  # type: ignore[arg-type]
    for bad_cfg in ({"coarse_step_deg": 0.0}, {"max_shift_m": -1.0}, {"fine_span_deg": -1.0},
                    {"coarse_step_deg": 45.0}, {"highpass_px": float("nan")}, {"max_shift_m": 1e5},
                    {"fine_step_deg": 1e-4}, {"fine_span_deg": 360.0}, {"rival_shift_m": 0.0}):
        with pytest.raises(ConfigError):
            DenseConfig(**bad_cfg)
