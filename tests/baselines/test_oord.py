"""The OORD benchmark preprocessing: bin cut-offs, bicubic resize, fixed-resolution Cartesian image."""

from __future__ import annotations

import numpy as np

from reradar_core.baselines.oord import oord_cartesian_image, oord_polar_image, suppress_range


def test_bins_below_60_are_zeroed_and_bins_from_max_bin_cut():
    power = np.ones((8, 4000), np.float32)
    out = suppress_range(power)
    assert out.shape == (8, 3768)
    assert np.all(out[:, :60] == 0.0) and np.all(out[:, 60:] == 1.0)
    assert np.all(power == 1.0)  # the input is not modified


def test_power_only_below_bin_60_gives_an_empty_image():
    power = np.zeros((400, 3768), np.float32)
    power[:, :60] = 1.0
    assert not np.any(oord_polar_image(power, 256, 256))
    assert not np.any(oord_cartesian_image(power, 0.0432, 1.2717, 256))


def test_resize_keeps_a_ramp_and_rings_at_a_step_as_bicubic_does():
    """(A, R) -> (num_azis, num_bins). A linear ramp along range stays linear away from the edges (the
    kernel is symmetric and sums to one); a step overshoots on both sides, which only a kernel with negative
    lobes (bicubic, not area or bilinear) does."""
    ramp = np.tile(np.arange(3768, dtype=np.float32) / 3768.0, (400, 1))
    out = oord_polar_image(ramp, 256, 128, min_bin=0)
    assert out.shape == (256, 128)
    centres = (np.arange(128) + 0.5) * 3768 / 128 - 0.5  # input bin at each output column's centre
    assert np.allclose(out[:, 8:-8], centres[8:-8] / 3768.0, atol=1e-4)

    step = np.zeros((400, 3768), np.float32)
    step[:, 1884:] = 1.0
    out = oord_polar_image(step, 256, 128, min_bin=0)
    assert out.min() < -0.01 and out.max() > 1.01


def test_cartesian_image_has_the_fixed_resolution_of_the_reference():
    """Pixel row i sits at x = (127.5 - i) * 1.2717 m, whatever the scan's own range: a target at 49.6-50.9 m
    on azimuth row 0 is seen only by row 88 (x = 50.23 m; rows 87 / 89 are at 51.50 / 48.96 m), between
    columns 127 and 128 (y = -/+ 0.64 m)."""
    for res, bins in ((0.0432, 3768), (0.0596, 3360)):
        power = np.zeros((400, bins), np.float32)
        power[0, int(49.6 / res) : int(50.9 / res)] = 1.0
        img = oord_cartesian_image(power, res, 1.2717, 256)
        assert img.shape == (256, 256)
        rows, cols = np.nonzero(img > 0.01)
        assert set(rows) == {88} and set(cols) == {127, 128}, (res, rows, cols)
