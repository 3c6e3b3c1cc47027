"""Shared fakes for the service tests: a fast deterministic feature extractor and synthetic scans."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from reradar_core.features import ScanFeatures
from reradar_core.geometry.cartesian import CartesianConfig, polar_to_metric
from reradar_core.io.scan import RadarScan

API_KEY = "test-key-0123456789abcdef"
N_KEYFRAMES = 6


def register_map_file(client: Any, map_file: Path, map_id: str) -> None:
    """POST ``map_file`` to ``/maps`` as ``map_id`` with the operator key (an httpx client) and check the 201."""
    with map_file.open("rb") as fh:
        r = client.post("/maps", data={"map_id": map_id}, files={"map_file": ("fake.h5", fh)},
                        headers={"X-API-Key": API_KEY})
    assert r.status_code == 201, r.text


class FakeExtractor:
    """Deterministic stand-in for the network (the HTTP layer is under test, not the model).

    Global descriptor: the scan's range profile (rotation invariant). Keypoints: returns above 0.5.
    Local descriptors: sin/cos of the keypoint's range at several frequencies (rotation invariant, distinct per
    range), so a scan matches itself and rotated copies of itself.
    """

    model_id = "fake-extractor"
    weights_sha256 = "f" * 64
    descriptor_dim = 32
    local_dim = 16  # 8 frequencies x (sin, cos): maps of another width are refused (MapRegistry.check_compatible)
    cartesian = CartesianConfig()

    def describe(self, scan: RadarScan) -> ScanFeatures:
        prof = scan.power.mean(axis=0)
        g = np.add.reduceat(prof, np.linspace(0, prof.size, 33).astype(int)[:-1]) + 1e-6
        az, rb = np.nonzero(scan.power > 0.5)
        r = scan.ranges_m[rb]
        xy = polar_to_metric(scan.azimuths[az], r)
        freqs = np.linspace(0.05, 2.0, 8)
        loc = np.concatenate([np.sin(r[:, None] * freqs), np.cos(r[:, None] * freqs)], axis=1)
        return ScanFeatures(g / np.linalg.norm(g), xy, loc / np.sqrt(8.0), scan.timestamp_us)

    def describe_batch(self, scans: list[RadarScan]) -> list[ScanFeatures]:
        return [self.describe(s) for s in scans]


def make_scan(seed: int, t_us: int, n_targets: int = 40, preset: str = "boreas") -> RadarScan:
    """A (400, 3360) boreas scan with ``n_targets`` bright point returns at distinct ranges."""
    rng = np.random.default_rng(seed)
    power = np.zeros((400, 3360), np.float32)
    bins = rng.choice(np.arange(100, 3300), n_targets, replace=False)
    az = rng.integers(0, 400, n_targets)
    power[az, bins] = 1.0
    return RadarScan.from_power(power, preset, start_time_us=t_us)


def damaged_png(scan: RadarScan) -> bytes:
    """``scan`` as a Navtech PNG whose compressed data is damaged past its first rows: the upload reads its header
    and its time, only the build's full decode refuses it (a scan the service cannot refuse before the build)."""
    from reradar_core.io.scan import encode_navtech_png_bytes

    data = bytearray(encode_navtech_png_bytes(scan))
    mid = len(data) * 3 // 4
    data[mid:mid + 64] = bytes(b ^ 0xFF for b in data[mid:mid + 64])
    return bytes(data)


def keyframe_poses() -> np.ndarray:
    return np.column_stack([np.arange(N_KEYFRAMES) * 40.0, np.arange(N_KEYFRAMES) * -3.0,
                            np.linspace(0.0, 1.0, N_KEYFRAMES)])


def keyframe_time(i: int) -> int:
    return 1_600_000_000_000_000 + i * 250_000


def count_model_loads(monkeypatch: Any) -> list[dict[str, Any]]:
    """Count ``DescriptorExtractor.from_file`` calls from now on (``monkeypatch``: the test's): returns the list
    that each load appends to, ``{"runtime", "threads": torch's thread count at the load, "extractor"}``."""
    import torch

    from reradar_core.model import DescriptorExtractor

    loads: list[dict[str, Any]] = []
    real_from_file = DescriptorExtractor.from_file.__func__  # type: ignore[attr-defined]

    def counting_from_file(cls: type[DescriptorExtractor], *args: Any, **kwargs: Any) -> DescriptorExtractor:
        ext = real_from_file(cls, *args, **kwargs)
        loads.append({"runtime": kwargs.get("runtime"), "threads": torch.get_num_threads(), "extractor": ext})
        return ext

    monkeypatch.setattr(DescriptorExtractor, "from_file", classmethod(counting_from_file))
    return loads


@contextmanager
def started_app(maps_dir: Path, **settings: Any) -> Iterator[Any]:
    """A ``TestClient`` of the app started (lifespan run) over ``maps_dir`` with ``FakeExtractor`` and the test
    operator key (``API_KEY``), no demo map; ``settings`` override ``Settings`` fields. Stopped on exit."""
    from fastapi.testclient import TestClient
    from pydantic import SecretStr

    from service.core.config import Settings
    from service.main import create_app

    cfg = Settings(maps_dir=maps_dir, load_demo_map=False, api_key=SecretStr(API_KEY), torch_threads=1, **settings)
    with TestClient(create_app(cfg, FakeExtractor())) as client:
        yield client


def upload_map_file(client: Any, map_file: Path, map_id: str) -> Any:
    """POST ``map_file`` to ``/maps`` as ``map_id`` with the operator key; the response."""
    with map_file.open("rb") as fh:
        return client.post("/maps", data={"map_id": map_id}, files={"map_file": ("fake.h5", fh)},
                           headers={"X-API-Key": API_KEY})
