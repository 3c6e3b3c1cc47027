"""Retrieval: exact FAISS search matches brute force; HNSW/IVF find the same nearest neighbours; the exact
Euclidean index and ``GlobalIndex.distances`` agree with numpy; a map database localizes through it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from maps.database import MapDatabase
from maps.store import MapMetadata, write_map
from reradar_core.errors import ConfigError
from reradar_core.features import ScanFeatures
from reradar_core.geometry.se2 import compose, inverse, transform_points
from reradar_core.retrieval import EuclideanIndex, GlobalIndex, IndexConfig, similarity_to_distance


def _unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def test_flat_matches_brute_force_and_auto_switches() -> None:
    rng = np.random.default_rng(0)
    x = _unit(rng.normal(size=(500, 32)))
    q = _unit(x[[3, 100, 499]] + 0.05 * rng.normal(size=(3, 32)))
    idx = GlobalIndex(x, IndexConfig(kind="auto", exact_max_size=1000))
    assert idx.kind == "flat"
    ids, sims = idx.search(q, 5)
    brute = np.argsort(-(q @ x.T), axis=1)[:, :5]
    np.testing.assert_array_equal(ids, brute)
    np.testing.assert_allclose(sims[:, 0], np.sum(q * x[brute[:, 0]], axis=1), rtol=1e-5)
    assert GlobalIndex(x, IndexConfig(kind="auto", exact_max_size=100)).kind == "ivf"


@pytest.mark.parametrize("kind", ["hnsw", "ivf"])
def test_approximate_indexes_find_the_true_neighbour(kind: str) -> None:
    rng = np.random.default_rng(1)
    x = _unit(rng.normal(size=(4000, 32)))
    targets = rng.choice(4000, 20, replace=False)
    q = _unit(x[targets] + 0.02 * rng.normal(size=(20, 32)))
    idx = GlobalIndex(x, IndexConfig(kind=kind, ivf_nlist=32, ivf_nprobe=8))
    assert idx.kind == kind
    ids, _ = idx.search(q, 3)
    np.testing.assert_array_equal(ids[:, 0], targets)
    if kind == "ivf":  # the compacted (serialised and reloaded) lists keep nprobe and the stored vectors
        assert idx._index.nprobe == 8
        np.testing.assert_array_equal(idx.vector(int(targets[0])), x[targets[0]].astype(np.float32))


def test_distance_and_errors() -> None:
    np.testing.assert_allclose(similarity_to_distance(np.array([1.0, 0.0, -1.0])), [0.0, np.sqrt(2), 2.0])
    idx = GlobalIndex(_unit(np.random.default_rng(2).normal(size=(3, 8))))
    ids, _ = idx.search(np.ones(8, np.float32) / np.sqrt(8), 10)
    assert ids.shape == (1, 3)  # k clipped to the map size
    with pytest.raises(ConfigError):
        idx.search(np.ones(9, np.float32), 1)
    with pytest.raises(ConfigError):
        IndexConfig(kind="lsh")


def test_distances_match_numpy_for_both_indexes() -> None:
    rng = np.random.default_rng(4)
    x = _unit(rng.normal(size=(50, 16)))
    q = _unit(rng.normal(size=16))
    expect = np.linalg.norm(x - q, axis=1)
    np.testing.assert_allclose(GlobalIndex(x).distances(q), expect, atol=1e-5)
    raw = rng.normal(size=(50, 16)) * 3.0  # not unit vectors: only the exact index is meaningful
    np.testing.assert_allclose(EuclideanIndex(raw).distances(q), np.linalg.norm(raw - q, axis=1), atol=1e-4)


def test_map_database_localizes_a_keyframe_seen_from_a_known_offset(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    n, c = 12, 16
    feats = []
    for i in range(n):
        k = 80
        feats.append(ScanFeatures(_unit(rng.normal(size=32)), rng.uniform(-70, 70, (k, 2)),
                                  _unit(rng.normal(size=(k, c))), i * 250_000))
    poses = np.column_stack([np.arange(n) * 30.0, np.arange(n) * 5.0, np.linspace(-1, 1, n)])
    meta = MapMetadata("m", "h" * 64, "boreas", 201, 0.64, 32, c)
    db = MapDatabase.open(write_map(tmp_path / "m.h5", meta, feats, poses), "m", "h" * 64)
    T_kf_q = np.array([3.0, 1.0, 0.2])
    kf = feats[7]
    pts = transform_points(inverse(T_kf_q), kf.keypoints_xy_m.astype(np.float64))
    query = ScanFeatures(_unit(kf.global_descriptor + 0.1 * rng.normal(size=32)), pts,
                         kf.local_descriptors.astype(np.float32), 0)
    assert db.retrieve(query.global_descriptor, 3)[0].keyframe_id == 7
    res = db.localize(query)
    assert res.candidates[0].keyframe_id == 7 and res.candidates[0].rank == 0
    assert res.localized and res.T_map_query is not None
    np.testing.assert_allclose(res.T_map_query, compose(poses[7], T_kf_q), atol=1e-3)
    assert {"retrieve_ms", "read_ms", "verify_ms"} <= set(res.timings_ms)
    assert db.map.global_descriptors is None  # released to the index; rows come from disk
    np.testing.assert_allclose(db.map.read_keyframe(7).global_descriptor, feats[7].global_descriptor, atol=1e-7)
    db.close()
