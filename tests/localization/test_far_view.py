"""The far view (``localization.far_view``): a refused near answer is looked at again over the whole range."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.se2 import inverse, transform_points
from reradar_core.localization import FarViewConfig, InMemoryKeyframes, Localizer, localize_two_views
from reradar_core.localization.far_view import VIEW_FAR, VIEW_NEAR
from reradar_core.retrieval import GlobalIndex


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _keyframe(rng: np.random.Generator, ts: int, reach_m: float) -> ScanFeatures:
    kps = rng.uniform(-reach_m, reach_m, size=(150, 2))
    return ScanFeatures(_unit(rng.normal(size=16)).astype(np.float32), kps.astype(np.float32),
                        _unit(rng.normal(size=(150, 32))).astype(np.float16), ts)


def _seen_from(kf: ScanFeatures, T_kf_query: np.ndarray, rng: np.random.Generator) -> ScanFeatures:
    """The keyframe's landmarks (70 %) and descriptors seen from T_kf_query, with 30 unrelated points."""
    sel = np.sort(rng.choice(len(kf.keypoints_xy_m), 105, replace=False))
    pts = transform_points(inverse(T_kf_query), kf.keypoints_xy_m[sel].astype(np.float64))
    pts += rng.normal(scale=0.1, size=pts.shape)
    desc = kf.local_descriptors[sel].astype(np.float32) + rng.normal(scale=0.05, size=(105, 32))
    out = rng.uniform(-60, 60, size=(30, 2))
    g = _unit(kf.global_descriptor.astype(np.float64) + rng.normal(scale=0.05, size=16)).astype(np.float32)
    return ScanFeatures(g, np.vstack([pts, out]).astype(np.float32),
                        _unit(np.vstack([desc, rng.normal(size=(30, 32))])).astype(np.float16), 10**9)


def _map(kfs: list[ScanFeatures], poses: np.ndarray) -> Localizer:
    return Localizer(GlobalIndex(np.stack([k.global_descriptor for k in kfs])), InMemoryKeyframes(kfs, poses),
                     preload=True)


@pytest.fixture(scope="module")
def two_views() -> tuple[Localizer, Localizer, list[ScanFeatures], list[ScanFeatures], np.ndarray]:
    rng = np.random.default_rng(3)
    poses = np.column_stack([np.arange(6) * 400.0, np.zeros(6), np.zeros(6)])
    near = [_keyframe(rng, 1000 * i, 60.0) for i in range(6)]
    far = [_keyframe(rng, 1000 * i, 160.0) for i in range(6)]
    return _map(near, poses), _map(far, poses), near, far, poses


def test_config_geometry_and_validation() -> None:
    cfg = FarViewConfig()
    assert (cfg.cartesian.width_px, cfg.cartesian.resolution_m) == (257, 1.28)
    assert cfg.reach_m == pytest.approx(164.48)
    for bad in ({"width_px": 256}, {"width_px": 1}, {"resolution_m": 0.0}, {"landmark_z_q": -1.0},
                {"sparse_landmarks": -1}):
        with pytest.raises(ConfigError):
            FarViewConfig(**bad)


def test_a_refused_near_answer_is_answered_by_the_far_view(two_views) -> None:
    near_map, far_map, near_kfs, far_kfs, poses = two_views
    rng = np.random.default_rng(4)
    T_kf_query = np.array([3.0, -1.5, np.deg2rad(20.0)])
    # near view: nothing that persists (random landmarks); far view: keyframe 4 seen from T_kf_query
    near_q = _keyframe(rng, 10**9, 60.0)
    far_q = _seen_from(far_kfs[4], T_kf_query, rng)
    out = localize_two_views(near_map, near_q, far_map, lambda: far_q)
    assert out.near_result.status == "not_localized"
    assert out.view == VIEW_FAR and out.result.localized and out.result.best.keyframe_id == 4
    T_map_query = poses[4] + np.array([T_kf_query[0], T_kf_query[1], T_kf_query[2]])  # keyframe yaw 0
    np.testing.assert_allclose(out.result.T_map_query[:2], T_map_query[:2], atol=0.3)
    assert out.result.T_map_query[2] == pytest.approx(T_map_query[2], abs=np.deg2rad(1.0))


def test_a_localized_near_answer_never_computes_the_far_view(two_views) -> None:
    near_map, far_map, near_kfs, _, _ = two_views
    rng = np.random.default_rng(5)
    near_q = _seen_from(near_kfs[1], np.array([2.0, 1.0, 0.1]), rng)

    def far_features() -> ScanFeatures:
        raise AssertionError("the far view was computed for a localized query")

    out = localize_two_views(near_map, near_q, far_map, far_features)
    assert out.view == VIEW_NEAR and out.result is out.near_result
    assert out.result.localized and out.result.best.keyframe_id == 1


def test_without_a_far_view_the_refusal_stands(two_views) -> None:
    near_map, _, _, _, _ = two_views
    near_q = _keyframe(np.random.default_rng(6), 10**9, 60.0)
    out = localize_two_views(near_map, near_q, None, None)
    assert out.view == VIEW_NEAR and out.result.status == "not_localized"


def test_far_view_of_another_map_is_refused(two_views) -> None:
    near_map, _, _, far_kfs, poses = two_views
    other = _map(far_kfs[:3], poses[:3])
    near_q = _keyframe(np.random.default_rng(7), 10**9, 60.0)
    with pytest.raises(ConfigError, match="same map"):
        localize_two_views(near_map, near_q, other, lambda: near_q)


def test_a_refused_far_answer_names_the_far_descriptors_top_place(two_views) -> None:
    near_map, far_map, _, far_kfs, _ = two_views
    rng = np.random.default_rng(8)
    near_q = _keyframe(rng, 10**9, 60.0)
    # the far descriptor points at keyframe 2, but none of its landmarks persist: nothing verifies
    lost = _keyframe(rng, 10**9, 160.0)
    far_q = ScanFeatures(far_kfs[2].global_descriptor, lost.keypoints_xy_m, lost.local_descriptors, 10**9)
    out = localize_two_views(near_map, near_q, far_map, lambda: far_q)
    assert out.view == VIEW_FAR and not out.result.localized and out.near_sparse  # 150 landmarks < 512
    assert out.place_id == 2
    assert min(out.result.candidates, key=lambda c: c.rank).keyframe_id == 2
    # a near view full of landmarks (here: at least 100) keeps naming its own best-screened candidate
    full = localize_two_views(near_map, near_q, far_map, lambda: far_q, far_view=FarViewConfig(sparse_landmarks=100))
    assert full.view == VIEW_FAR and not full.near_sparse
    assert full.place_id == full.near_result.best.keyframe_id


def test_a_localized_answer_names_its_winner(two_views) -> None:
    near_map, far_map, near_kfs, _, _ = two_views
    near_q = _seen_from(near_kfs[3], np.array([1.0, 0.5, -0.2]), np.random.default_rng(9))
    out = localize_two_views(near_map, near_q, far_map, None)
    assert out.result.localized and out.place_id == out.result.best.keyframe_id == 3


def test_a_far_answer_to_a_lost_track_stays_marked_lost_and_counts_both_views_time(two_views) -> None:
    """QA session 34: a tracked request whose registration failed and whose global fallback the far view answered
    came back ``tracking_lost: false`` without ``track_ms``; the near view's stage times were missing too."""
    from reradar_core.localization import PosePrior
    from reradar_core.localization.far_view import far_fallback

    near_map, far_map, _, far_kfs, poses = two_views
    rng = np.random.default_rng(8)
    near_q = _keyframe(rng, 10**9, 60.0)  # nothing the near view can register
    far_q = _seen_from(far_kfs[2], np.array([1.0, 2.0, 0.2]), rng)
    prior = PosePrior(poses[2] + np.array([1.0, 2.0, 0.2]), sigma_xy_m=1.0, sigma_yaw_rad=np.deg2rad(2.0))
    tracked = near_map.track(near_q, prior)
    assert tracked.tracking_lost and tracked.mode == "global" and not tracked.localized
    near_times = dict(tracked.timings_ms)
    out = far_fallback(tracked, near_map, near_q, far_map, lambda: far_q)
    assert out.view == VIEW_FAR and out.result.localized and out.result.best.keyframe_id == 2
    assert out.result.tracking_lost is True
    assert out.result.timings_ms["track_ms"] == pytest.approx(near_times["track_ms"])
    assert out.result.timings_ms["verify_ms"] > near_times["verify_ms"] > 0
    assert out.near_result is tracked and tracked.timings_ms == near_times  # the near answer is left as it was


def _far_image(seed: int, spots: int) -> np.ndarray:
    """A far-view dense image (``matching.dense.dense_image``) of a polar scan with ``spots`` bright reflectors."""
    from reradar_core.io.scan import RadarScan
    from reradar_core.matching.dense import dense_image

    rng = np.random.default_rng(seed)
    power = rng.uniform(0.0, 0.08, size=(400, 700)).astype(np.float32)
    for _ in range(spots):
        a, r = rng.integers(0, 400), rng.integers(100, 650)
        power[a:a + 2, r:r + 5] = 0.9
    scan = RadarScan(power, np.arange(400) * 2 * np.pi / 400, np.arange(400, dtype=np.int64) * 625, 0.25, 0.0)
    return dense_image(scan, FarViewConfig().cartesian)


def _refused_far_query(two_views, seed: int):
    """A query both views refuse (nothing persists in either), whose far descriptor points at keyframe 2."""
    _, _, _, far_kfs, _ = two_views
    rng = np.random.default_rng(seed)
    near_q = _keyframe(rng, 10**9, 60.0)
    lost = _keyframe(rng, 10**9, 160.0)
    return near_q, ScanFeatures(far_kfs[2].global_descriptor, lost.keypoints_xy_m, lost.local_descriptors, 10**9)


def test_dense_registration_localizes_what_both_views_refused(two_views) -> None:
    near_map, far_map, _, _, poses = two_views
    near_q, far_q = _refused_far_query(two_views, 11)
    images = {j: _far_image(100 + j, 60) for j in range(6)}
    calls: list[int] = []

    def keyframe_image(j: int) -> np.ndarray:
        calls.append(j)
        return images[j]

    # the query sees exactly what keyframe 2 saw: the dense pose is the keyframe's own
    out = localize_two_views(near_map, near_q, far_map, lambda: far_q, dense_query=lambda: images[2],
                             dense_keyframe=keyframe_image)
    assert out.view == VIEW_FAR and out.registration == "dense" and out.result.localized
    assert out.result.best.keyframe_id == 2 and out.place_id == 2
    np.testing.assert_allclose(out.result.T_map_query, poses[2], atol=0.05)
    assert out.heading_margin >= FarViewConfig().dense_min_heading_margin
    assert out.result.confidence == pytest.approx(FarViewConfig().dense_answer_confidence(out.heading_margin))
    assert out.result.best.num_inliers == 0
    # the dense answers' calibrated covariance: 0.42 m along the vehicle's heading and across it, 0.4 deg
    cov = out.result.pose_covariance
    yaw = out.result.T_map_query[2]
    along, across = np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])
    assert along @ cov[:2, :2] @ along == pytest.approx(0.42 ** 2)
    assert across @ cov[:2, :2] @ across == pytest.approx(0.42 ** 2)
    assert cov[2, 2] == pytest.approx(0.007 ** 2) and np.allclose(cov, cov.T)
    # and the rotation into the map frame: an anisotropic setting keeps its axes along / across the heading
    aniso = FarViewConfig(dense_pose_sigma=(0.1, 1.0, 0.01)).dense_pose_covariance(np.array([0.0, 0.0, np.pi / 2]))
    np.testing.assert_allclose(aniso[:2, :2], np.diag([1.0, 0.01]), atol=1e-12)  # heading north: along = map y
    for yaw in np.linspace(-3.1, 3.1, 37):  # exactly symmetric at any heading (QA session 41: 1e-18 apart)
        cov = FarViewConfig(dense_pose_sigma=(0.3, 0.7, 0.01)).dense_pose_covariance(np.array([5.0, -2.0, yaw]))
        assert np.array_equal(cov, cov.T)
    assert "dense_ms" in out.result.timings_ms and len(calls) == FarViewConfig().dense_candidates
    # the winner's entry in the candidate list is the dense answer, not the far view's refusal
    entry = next(c for c in out.result.candidates if c.keyframe_id == 2)
    assert entry is out.result.best and entry.reason is None and entry.T_keyframe_query is not None


@pytest.mark.parametrize(("heading", "shift", "edge", "localized"), [
    (0.30, 0.60, False, True),
    (0.04, 0.60, False, False),  # aligns about as well at another heading
    (0.30, 0.20, False, False),  # aligns about as well one step along itself (a bank, a row of posts)
    (0.30, 0.60, True, False),   # the peak on the window's border: the shift may lie beyond it
])
def test_the_dense_answer_needs_a_unique_heading_and_a_unique_shift_inside_the_window(
        two_views, monkeypatch: pytest.MonkeyPatch, heading: float, shift: float, edge: bool, localized: bool) -> None:
    import time

    from reradar_core.localization import far_view as fv
    from reradar_core.matching.dense import DenseRegistration

    near_map, far_map, _, _, _ = two_views
    near_q, far_q = _refused_far_query(two_views, 14)
    reg = DenseRegistration(np.array([1.0, -2.0, 0.1]), 0.4, heading, 0.4, shift, edge)
    monkeypatch.setattr(fv, "register_dense_best", lambda *a, **k: (0, reg))

    def slow_query_image() -> np.ndarray:
        time.sleep(0.3)  # the query image is the caller's stage: not in dense_ms
        return np.zeros((257, 257), np.float32)

    out = localize_two_views(near_map, near_q, far_map, lambda: far_q, dense_query=slow_query_image,
                             dense_keyframe=lambda j: np.zeros((257, 257), np.float32))
    assert out.result.localized is localized and out.registration == ("dense" if localized else "landmarks")
    assert out.heading_margin == heading and out.result.timings_ms["dense_ms"] < 300


def test_dense_registration_refuses_a_scene_that_aligns_at_every_heading(two_views) -> None:
    near_map, far_map, _, _, _ = two_views
    near_q, far_q = _refused_far_query(two_views, 12)
    empty = {j: _far_image(200 + j, 0) for j in range(6)}  # speckle only
    out = localize_two_views(near_map, near_q, far_map, lambda: far_q, dense_query=lambda: _far_image(300, 0),
                             dense_keyframe=lambda j: empty[j])
    assert out.view == VIEW_FAR and not out.result.localized and out.registration == "landmarks"
    assert out.heading_margin is not None and out.heading_margin < FarViewConfig().dense_min_heading_margin
    assert out.place_id == 2 and "dense_ms" in out.result.timings_ms


def test_dense_registration_only_for_a_near_view_with_little_in_view(two_views) -> None:
    near_map, far_map, _, _, _ = two_views
    near_q, far_q = _refused_far_query(two_views, 13)

    def never(*_: object) -> np.ndarray:
        raise AssertionError("a dense image was computed for a full near view")

    out = localize_two_views(near_map, near_q, far_map, lambda: far_q, far_view=FarViewConfig(sparse_landmarks=100),
                             dense_query=never, dense_keyframe=never)
    assert not out.result.localized and out.registration == "landmarks" and out.heading_margin is None


def test_dense_settings_are_validated() -> None:
    for bad in ({"dense_candidates": 0}, {"dense_candidates": 2.5}, {"dense_min_heading_margin": 0.0},
                {"dense_min_shift_margin": 1.0}, {"dense_min_shift_margin": -0.1},
                {"dense_pose_sigma": (0.2, 0.5)}, {"dense_pose_sigma": (0.0, 0.5, 0.01)},
                {"dense_confidence": (1.0, -2.0)}, {"dense_confidence": (1.0,)}):
        with pytest.raises(ConfigError):
            FarViewConfig(**bad)
    cfg = FarViewConfig()
    assert cfg.dense_answer_confidence(0.05) == pytest.approx(0.95, abs=0.01)
    assert cfg.dense_answer_confidence(0.0) < 1e-6 and cfg.dense_answer_confidence(0.3) > 0.999
