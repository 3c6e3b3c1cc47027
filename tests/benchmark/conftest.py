"""Two tiny synthetic sequences (a loop driven twice) written by the tests into a temp folder."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.benchmark.synthetic import loop_poses, synthetic_world, write_synthetic_sequence


@pytest.fixture(scope="session")
def loop_sequences(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench_seq")
    world = synthetic_world(seed=5)
    db = write_synthetic_sequence(root / "db-run", world, loop_poses(12), seed=1)
    q = write_synthetic_sequence(root / "query-run", world, loop_poses(12, phase=0.08, lateral_m=2.0), seed=2,
                                 t0_us=1_700_000_000_000_000)
    return root, db, q


@pytest.fixture()
def cache_env(tmp_path, monkeypatch):
    monkeypatch.setenv("RERADAR_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache"


def pose_grid() -> np.ndarray:
    return np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [100.0, 0.0, 0.0]])
