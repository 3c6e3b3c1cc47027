"""ResNet18-NetVLAD as the OORD reference: calibration quirks (position-normalised k-means input, alpha from
neighbour indices), NetVLAD bias from the centre norm, raw [0, 1] input."""

from __future__ import annotations

import numpy as np

from reradar_core.baselines.resnet_netvlad import (
    ResNetNetVLAD,
    netvlad_numpy,
    normalise_positions,
    reference_alpha,
)
from reradar_core.io.scan import RadarScan


def test_alpha_comes_from_the_indices_of_the_two_nearest_training_descriptors():
    """Centre 0.1: neighbours index 0 then 1 (1 - 0 = 1); centre 29.9: index 3 then 2 (4 - 9 = -5);
    mean -2, alpha = -ln(0.01) / -2."""
    train = np.array([[0.0], [10.0], [20.0], [30.0]], np.float32)
    centres = np.array([[0.1], [29.9]], np.float32)
    assert np.isclose(reference_alpha(centres, train), -np.log(0.01) / -2.0)


def test_calibration_descriptors_are_normalised_over_positions():
    x = np.array([[3.0, 0.0], [4.0, 2.0]], np.float32)
    assert np.allclose(normalise_positions(x), [[0.6, 0.0], [0.8, 1.0]])


def test_netvlad_bias_uses_the_centre_norm_not_its_square():
    """x = (1, 0); c1 = (2, 0): 2 c1.x - |c1| = 2; c2 = (0.5, 0): 1 - 0.5 = 0.5. With a large alpha all
    weight goes to c1 (the squared norm would prefer c2: 0 vs 0.75), so c2's block is empty."""
    c = np.array([[2.0, 0.0], [0.5, 0.0]], np.float32)
    v = netvlad_numpy(np.array([[3.0, 0.0]], np.float32), c, alpha=1e3).reshape(2, 2)
    assert np.allclose(v[1], 0.0, atol=1e-6)
    assert np.allclose(v[0], [-1.0, 0.0], atol=1e-6)  # residual (1, 0) - (2, 0), intra-normalised


def test_prepare_and_fit_on_tiny_scans():
    rng = np.random.default_rng(0)
    scans = [RadarScan((rng.random((400, 800)) ** 4).astype(np.float32), np.arange(400) * np.pi / 200,
                       np.zeros(400, np.int64), 0.0596) for _ in range(6)]
    m = ResNetNetVLAD()
    prep = [m.prepare(s) for s in scans]
    assert prep[0]["local"].shape == (16, 512)  # 128 x 128 input -> 4 x 4 conv5 positions
    m.fit(prep)
    assert m.centres is not None and m.centres.shape == (64, 512)
    d = m.describe_prepared(prep[0])
    assert d.shape == (64 * 512,) and np.isclose(np.linalg.norm(d), 1.0, atol=1e-5)
