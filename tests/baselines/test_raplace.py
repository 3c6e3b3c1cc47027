"""RaPlace as the OORD reference: DC row kept, x0.25 shrink, z-score, frequency-axis correlation score."""

from __future__ import annotations

import numpy as np

from reradar_core.baselines.raplace import (
    RaPlace,
    RaPlaceNoDC,
    radon_skimage,
    shrink_skimage,
    sino_fft_descriptor,
)
from reradar_core.io.scan import RadarScan


def _scan(seed: int = 0) -> RadarScan:
    rng = np.random.default_rng(seed)
    power = (rng.random((400, 3768)) ** 8).astype(np.float32)  # sparse bright returns
    return RadarScan(power, np.arange(400) * 2 * np.pi / 400, np.zeros(400, np.int64), 0.0432)


def test_radon_of_a_vertical_line_puts_all_mass_in_its_column_at_zero_degrees():
    img = np.zeros((64, 64), np.float32)
    img[8:56, 40] = 1.0
    sino = radon_skimage(img, 180)
    assert sino.shape == (64, 180)  # offsets x angles, as skimage
    assert int(np.argmax(sino[:, 0])) == 40 and np.isclose(sino[40, 0], 48.0)
    assert np.isclose(sino[:, 90].max(), 1.0, atol=0.05)  # at 90 degrees the line is seen edge-on


def test_shrink_of_a_constant_image_is_constant_with_the_rounded_shape():
    out = shrink_skimage(np.full((256, 180), 3.0), 0.25)
    assert out.shape == (64, 45)
    assert np.allclose(out, 3.0)


def test_descriptor_keeps_the_dc_row_which_dominates_a_non_negative_image():
    """|FFT| row 0 of a non-negative sinogram column is its sum, no smaller than any other frequency; after
    the z-score it is still the largest entry of every angle column. The variant drops that row."""
    rng = np.random.default_rng(1)
    cart = (rng.random((256, 256)) ** 6).astype(np.float32)
    d = sino_fft_descriptor(cart)
    assert d.shape == (32, 45)
    assert np.all(np.argmax(d, axis=0) == 0)
    assert np.isclose(d.mean(), 0.0, atol=1e-9) and np.isclose(d.std(), 1.0)
    nodc = RaPlaceNoDC().prepare(_scan())["radon_fft"]
    assert nodc.shape == (180, 128)  # rfft of 256 offsets = 129 bins, DC removed


def test_distance_is_the_gap_between_auto_and_cross_correlation_peaks():
    """distance(q, i) = |max_s c_qq - max_s c_qi| with s a shift along the frequency axis: zero for q
    itself and for q rolled along frequency, not for q rolled along angle (no rotation search)."""
    m = RaPlace()
    rng = np.random.default_rng(2)
    q, other = ((x - x.mean()) / x.std() for x in rng.normal(size=(2, 32, 45)))
    db = [q, np.roll(q, 5, axis=0), np.roll(q, 9, axis=1), other]
    d = m.distance(q, m.build_index(db))
    assert np.isclose(d[0], 0.0, atol=1e-9) and np.isclose(d[1], 0.0, atol=1e-9)
    assert d[2] > 100.0 and d[3] > 100.0  # of an autocorrelation peak of 1,440
    auto = float((q * q).sum())  # shift-0 autocorrelation of a z-scored descriptor = number of values
    assert np.isclose(auto, q.size)
    cross = max(float((np.roll(q, s, axis=0) * other).sum()) for s in range(q.shape[0]))
    assert np.isclose(d[3], abs(auto - cross))
    assert not m.provides_heading and m.estimate_heading(q, m.build_index(db), 0) is None
