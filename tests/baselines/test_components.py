"""Known-answer checks of shared building blocks: Radon (variant), VLAD, k-means++, ResNet-18, landmark memo.

The reference-specific checks live in ``test_<method>.py``."""

from __future__ import annotations

import numpy as np
import torch

from reradar_core.baselines.kmeans import kmeans, kmeans_plus_plus_init
from reradar_core.baselines.radvlad import vlad
from reradar_core.baselines.raplace import radon_sinogram
from reradar_core.baselines.resnet18 import ResNet18


def test_variant_radon_of_a_vertical_line_concentrates_at_angle_zero():
    img = np.zeros((65, 65), np.float32)
    img[8:57, 40] = 1.0  # vertical line, column 40 (8 px right of the centre column 32)
    sino = radon_sinogram(img, 180)
    assert sino.shape == (180, 65)
    # at 0 deg the columns are summed as they are: all mass in column 40
    assert int(np.argmax(sino[0])) == 40
    assert sino[0].max() > 0.9 * sino[0].sum()
    # the peak over all angles is at 0 degrees
    assert np.unravel_index(np.argmax(sino), sino.shape)[0] in (0, 179)


def test_vlad_residual_sums_known_answer():
    centres = np.array([[0.0, 0.0], [10.0, 0.0]], np.float32)
    feats = np.array([[1.0, 0.0], [0.0, 1.0], [11.0, 0.0]], np.float32)
    v = vlad(feats, centres).reshape(2, 2)
    raw = np.array([[1.0, 1.0], [1.0, 0.0]])  # residuals of cluster 0: (1,0)+(0,1); cluster 1: (1,0)
    expect = np.sign(raw) * np.sqrt(np.abs(raw))
    expect /= np.linalg.norm(expect)
    assert np.allclose(v, expect, atol=1e-6)


def test_vlad_is_invariant_to_feature_order():
    rng = np.random.default_rng(0)
    f = rng.normal(size=(50, 8)).astype(np.float32)
    c = rng.normal(size=(4, 8)).astype(np.float32)
    assert np.allclose(vlad(f, c), vlad(f[::-1], c))


def test_kmeans_recovers_separated_clusters():
    rng = np.random.default_rng(1)
    true = np.array([[0, 0], [20, 0], [0, 20], [20, 20]], np.float32)
    x = np.concatenate([t + rng.normal(scale=0.5, size=(200, 2)) for t in true]).astype(np.float32)
    init = kmeans_plus_plus_init(x, 4, seed=0)
    assert np.allclose(init, kmeans_plus_plus_init(x, 4, seed=0))  # deterministic
    c = kmeans(x, 4, seed=0)
    d = np.linalg.norm(c[:, None] - true[None], axis=-1).min(axis=0)
    assert np.all(d < 0.3), d


def test_resnet18_shapes_and_parameter_count():
    torch.manual_seed(0)
    net = ResNet18(3).eval()
    with torch.no_grad():
        f = net(torch.zeros(1, 3, 128, 128))
    assert f.shape == (1, 512, 4, 4)
    n = sum(p.numel() for p in net.parameters())
    assert n == 11_176_512  # torchvision resnet18 without the fc layer


def test_landmarks_are_memoised_per_scan_object():
    from reradar_core.baselines.base import landmarks_for
    from reradar_core.benchmark.synthetic import render_scan, synthetic_world
    from reradar_core.landmarks import Cen2018Config, detect_landmarks

    w = synthetic_world(seed=1)
    a = render_scan(w, np.zeros(3), noise_seed=0)
    b = render_scan(w, np.array([5.0, 0.0, 0.0]), noise_seed=1)
    la = landmarks_for(a)
    assert landmarks_for(a, Cen2018Config()) is la  # None and the default config are the same detector
    assert np.array_equal(la.xy_m, detect_landmarks(a).xy_m)
    lb = landmarks_for(b)
    assert lb is not la and np.array_equal(lb.xy_m, detect_landmarks(b).xy_m)
