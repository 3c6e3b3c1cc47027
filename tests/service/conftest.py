"""Fixtures for the service tests: a fast fake feature extractor, synthetic scans, a live uvicorn server."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from maps.build import build_map
from service.core.config import Settings
from service.demo import serve_in_thread

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import (  # noqa: E402
    API_KEY,
    FakeExtractor,
    keyframe_poses,
    keyframe_time,
    make_scan,
)


@pytest.fixture(scope="session")
def fake_extractor() -> FakeExtractor:
    return FakeExtractor()


@pytest.fixture(scope="session")
def fake_map(tmp_path_factory: pytest.TempPathFactory, fake_extractor: FakeExtractor) -> Path:
    out = tmp_path_factory.mktemp("built") / "fake.h5"
    return build_map(out, fake_extractor, lambda i: make_scan(i, keyframe_time(i)), keyframe_poses(),
                     radar_preset="boreas", name="fake", batch_size=4)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory, fake_extractor: FakeExtractor) -> Iterator[tuple[str, Path]]:
    """A live uvicorn server on 127.0.0.1 with an empty maps dir; yields (base URL, maps dir)."""
    maps_dir = tmp_path_factory.mktemp("maps")
    settings = Settings(maps_dir=maps_dir, load_demo_map=False, api_key=API_KEY, max_upload_mb=3.0,
                        max_map_upload_mb=8.0, torch_threads=1)
    with serve_in_thread(settings, fake_extractor) as url:
        yield url, maps_dir

