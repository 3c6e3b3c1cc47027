"""The ``smoke`` suite end to end with ReRadar in the loop (untrained, seeded network: harness check only),
plus the stage-timing table and the yaw-consistency curve."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from reradar_core.baselines import make_method
from reradar_core.baselines.ours import Ours
from reradar_core.benchmark.extras import add_timing, add_yaw_consistency
from reradar_core.benchmark.results import results_markdown
from reradar_core.benchmark.runner import BenchConfig, run_benchmark
from reradar_core.benchmark.suites import pairs_from_suite
from reradar_core.benchmark.timing import STAGES
from reradar_core.benchmark.yaw import yaw_consistency


@pytest.fixture(scope="module")
def untrained_extractor():
    from reradar_core.model import DescriptorExtractor, DescriptorNet, ModelConfig

    torch.manual_seed(0)
    return DescriptorExtractor(DescriptorNet(ModelConfig()))


def test_smoke_suite_bench_with_ours(tmp_path, monkeypatch, untrained_extractor):
    monkeypatch.setenv("RERADAR_CACHE_DIR", str(tmp_path / "cache"))
    pairs, radius = pairs_from_suite("smoke", limit=10, progress=False)
    assert radius == 20.0 and len(pairs) == 1 and len(pairs[0].query) == 10
    ours = Ours(untrained_extractor, name="ours-untrained")
    methods = [ours, make_method("ringkey"), make_method("raplace")]
    cfg = BenchConfig(radius_m=radius, progress=False, rotation_limit=5)
    res = run_benchmark(pairs, methods, tmp_path / "out", cfg, suite="smoke")
    row = res["sequences"][pairs[0].name]["ours-untrained"]
    assert row["n_queries"] == 10 and row["sr"] is not None  # pose method -> SR applicable
    if row["sr"] > 0:
        assert row["e_r_deg"] < 10.0 and row["e_t_m"] < radius
    stress = res["rotation_stress"][pairs[0].name]
    assert set(stress) == {"ours-untrained", "ringkey", "raplace"}
    assert all(v["n_queries"] == 5 for v in stress.values())

    t = add_timing(res, ours, pairs[0], cfg, n_scans=2, threads=1)
    assert list(t["stages_ms"]) == list(STAGES)
    s = t["stages_ms"]
    parts = sum(s[k]["mean"] for k in STAGES[:-1])
    assert s["total"]["mean"] == pytest.approx(parts, rel=0.05)
    assert "Stage timings" in results_markdown(res)

    p = add_yaw_consistency(res, [ours], pairs[0], tmp_path / "out", n_scans=1)
    assert p is not None and p.is_file()
    curve = next(iter(res["yaw_consistency"].values()))
    assert curve["consistency"][0] == pytest.approx(1.0, abs=1e-5)  # theta = 0: identical maps


class _PooledImage:
    """F' = 8x8 average pooling of [I, I^2]: rotation-equivariant with invariant channels."""

    def __init__(self, gradient: bool = False) -> None:
        self.gradient = gradient

    def cartesian_image(self, scan):
        return scan

    def run_images(self, imgs):
        x = torch.as_tensor(np.asarray(imgs, np.float32))[:, None]
        if self.gradient:  # d/dcol, d/drow: channels rotate with the image -> not invariant channels
            ch = torch.cat([x[..., :, 1:] - x[..., :, :-1], x[..., 1:, :-1] - x[..., :-1, :-1]][:1] +
                           [torch.nn.functional.pad(x[..., 1:, :] - x[..., :-1, :], (0, 0, 0, 1))[..., :, :-1]],
                           dim=1)
        else:
            ch = torch.cat([x, x * x], dim=1)
        f = torch.nn.functional.avg_pool2d(ch, 8, 8)
        return np.zeros((len(x), 1), np.float32), f.numpy()


def test_yaw_consistency_separates_equivariant_from_non_equivariant_maps():
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:201, 0:201]
    img = np.zeros((201, 201), np.float32)
    for _ in range(30):  # smooth blobs: well sampled under rotation
        cy, cx = rng.uniform(40, 160, 2)
        img += np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * 6.0**2)).astype(np.float32)
    angles = np.array([0.0, 45.0, 90.0, 135.0])
    eq = yaw_consistency(_PooledImage(), [img], angles)
    grad = yaw_consistency(_PooledImage(gradient=True), [img], angles)
    assert eq[0] == pytest.approx(1.0, abs=1e-6) and np.all(eq > 0.97), eq
    assert grad[2] < 0.5, grad  # gradients turned by 90 deg point another way: low cosine
