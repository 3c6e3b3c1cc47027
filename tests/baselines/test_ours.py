"""ReRadar behind the baseline interface: retrieval + landmark verification returns the known pose."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.baselines.ours import Ours, features_to_prepared, prepared_to_features
from reradar_core.features import ScanFeatures
from reradar_core.geometry.cartesian import CartesianConfig
from reradar_core.geometry.se2 import compose, inverse, transform_points


class _FakeExtractor:
    """Stands in for the network: features are given per test, ``describe`` is not used here."""

    model_id = "fake"
    weights_sha256 = "0" * 64
    descriptor_dim = 8
    cartesian = CartesianConfig()

    def describe(self, scan):  # pragma: no cover - not called
        raise AssertionError


def _keyframe(rng, n=60):
    xy = rng.uniform(-50, 50, size=(n, 2))
    desc = rng.normal(size=(n, 16))
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    g = rng.normal(size=8)
    return xy, desc, g / np.linalg.norm(g)


_DB_POSES = np.array([[0.0, 0.0, 0.0], [100.0, 50.0, 1.0], [30.0, -20.0, -2.0]])
_T_KF_Q = np.array([3.0, -1.5, 0.4])


def _query_at_keyframe_1(decoy: bool):
    """Three keyframes at ``_DB_POSES`` and a query at keyframe 1 offset by ``_T_KF_Q``; with ``decoy`` its global
    descriptor is closest to keyframe 2. Returns (ours, index, db, q)."""
    rng = np.random.default_rng(0)
    kfs = [_keyframe(rng) for _ in _DB_POSES]
    db = [features_to_prepared(ScanFeatures(g, xy, d, 0)) for xy, d, g in kfs]
    xy, d, g = kfs[1]
    g_q = kfs[2][2] * 0.9 + g * 0.1 if decoy else g
    q = features_to_prepared(ScanFeatures(g_q, transform_points(inverse(_T_KF_Q), xy), d, 0))
    ours = Ours(_FakeExtractor(), name="ours-test")
    return ours, ours.build_index([ours.describe_prepared(r) for r in db]), db, q


def test_localize_recovers_known_pose_and_reranks_by_inliers():
    ours, index, db, q = _query_at_keyframe_1(decoy=True)
    db_poses, T_kf_q = _DB_POSES, _T_KF_Q
    r = ours.localize(q, ours.describe_prepared(q), index, db, db_poses)
    assert r.index == 1  # re-ranked by inliers, not the descriptor's favourite (2)
    assert r.pose is not None
    expect = compose(db_poses[1], T_kf_q)
    assert np.allclose(r.pose[:2], expect[:2], atol=0.05)
    assert abs(r.pose[2] - expect[2]) < 1e-3
    assert abs(r.heading_rad - T_kf_q[2]) < 1e-3


def test_unverifiable_query_returns_no_pose():
    rng = np.random.default_rng(1)
    db_poses = np.zeros((2, 3))
    db = [features_to_prepared(ScanFeatures(g, xy, d, 0)) for xy, d, g in (_keyframe(rng), _keyframe(rng))]
    xy, d, g = _keyframe(rng)  # an unrelated place
    q = features_to_prepared(ScanFeatures(g, xy, d, 0))
    ours = Ours(_FakeExtractor(), name="ours-test")
    index = ours.build_index([ours.describe_prepared(p) for p in db])
    r = ours.localize(q, ours.describe_prepared(q), index, db, db_poses)
    assert r.pose is None and r.heading_rad is None


def test_prepared_round_trip():
    f = ScanFeatures(np.ones(4) / 2, np.zeros((3, 2)), np.ones((3, 5)) / np.sqrt(5), 123)
    g = prepared_to_features(features_to_prepared(f))
    assert g.timestamp_us == 123 and g.local_descriptors.dtype == np.float16
    assert np.allclose(g.global_descriptor, f.global_descriptor)


def test_far_suffix_names_a_separate_row_and_applies_to_recall_methods_only() -> None:
    from reradar_core.baselines import make_method, ours_model_names
    from reradar_core.errors import ConfigError

    with pytest.raises(ConfigError, match="ReRadar model without a far view"):
        make_method("raplace+far")
    model = ours_model_names()[0]
    m = make_method(model + "+far")
    assert m.name == model + "+far" and m.far_view is not None
    assert m.params()["far_view"] == [257, 1.28] and "far_view" not in make_method(model).params()


def test_dense_suffix_adds_the_far_view_and_its_dense_registration() -> None:
    from reradar_core.baselines import make_method, ours_model_names
    from reradar_core.baselines.ours import Ours
    from reradar_core.errors import ConfigError

    model = ours_model_names()[0]
    m = make_method(model + "+dense")
    assert m.name == model + "+dense" and m.far_view is not None and m.dense
    assert "dense" in m.params() and "dense" not in make_method(model + "+far").params()
    for bad in ("raplace+dense", model + "+far+dense", model + "+dense+far"):
        with pytest.raises(ConfigError, match="without a far view"):
            make_method(bad)
    with pytest.raises(ConfigError, match="step of the far view"):
        Ours(m.extractor, dense=True)


def test_new_poses_for_the_same_database_are_a_new_map():
    """QA session 38: the Localizer was kept per (id(index), id(db)), so poses shifted by 1 km answered the old pose."""
    ours, index, db, q = _query_at_keyframe_1(decoy=False)
    first = ours.localize(q, ours.describe_prepared(q), index, db, _DB_POSES)
    shifted = _DB_POSES + np.array([1000.0, 0.0, 0.0])
    again = ours.localize(q, ours.describe_prepared(q), index, db, shifted)
    assert first.pose is not None and again.pose is not None
    np.testing.assert_allclose(again.pose[:2], first.pose[:2] + [1000.0, 0.0], atol=1e-6)


@pytest.mark.parametrize("method", ["ringkey", "raplace", "radvlad", "referee"])
def test_describe_names_what_it_takes(method):
    from reradar_core.baselines import make_method
    from reradar_core.errors import ConfigError

    with pytest.raises(ConfigError, match=r"describe takes a RadarScan"):
        make_method(method).describe(np.zeros((400, 3360)))


def test_two_view_top1_reads_the_far_descriptor_only_for_a_sparse_near_view() -> None:
    """The two-view method's descriptor-alone place: the far descriptor's nearest keyframe when the near view holds
    fewer landmarks than ``FarViewConfig.sparse_landmarks``, else the near descriptor's (known answers: the near
    descriptor points at keyframe 0, the far one at keyframe 2)."""
    from reradar_core.baselines.ours import two_view_top1
    from reradar_core.localization import FarViewConfig
    from reradar_core.retrieval import GlobalIndex

    eye = np.eye(3, dtype=np.float32)
    near_index, far_index = GlobalIndex(eye), GlobalIndex(eye[::-1].copy())  # far keyframe 2 = near keyframe 0's

    def query(landmarks: int) -> dict:
        near = features_to_prepared(ScanFeatures(eye[0], np.zeros((landmarks, 2), np.float32),
                                                 np.zeros((landmarks, 16), np.float16), 0))
        return {**near, "far_global": eye[0]}

    assert two_view_top1(query(60), near_index, far_index, FarViewConfig()) == 2  # 60 < 512: sparse, far view
    assert two_view_top1(query(60), near_index, far_index, FarViewConfig(sparse_landmarks=60)) == 0  # full: near
    assert two_view_top1(query(512), near_index, far_index, FarViewConfig()) == 0
