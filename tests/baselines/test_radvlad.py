"""RadVLAD as the OORD reference: full 256-bin beam |FFT|, bin-60 cut-off, converged vocabulary, VLAD."""

from __future__ import annotations

import numpy as np

from reradar_core.baselines.radvlad import RadVLAD, RadVLADConfig, beam_fft_features
from reradar_core.io.scan import RadarScan


def _scan(power: np.ndarray) -> RadarScan:
    n = power.shape[0]
    return RadarScan(power, np.arange(n) * 2 * np.pi / n, np.zeros(n, np.int64), 0.0432)


def test_beam_features_keep_all_256_fft_bins_including_the_mirrored_half():
    rng = np.random.default_rng(0)
    f = beam_fft_features(rng.random((400, 3768)).astype(np.float32))
    assert f.shape == (256, 256)
    # |FFT| of a real beam: bin k mirrors bin 256 - k, so the upper half repeats the lower one
    assert np.allclose(f[:, 1:128], f[:, 255:128:-1], rtol=1e-5, atol=1e-5)
    assert f[:, 128:].sum() > 0.4 * f[:, 1:].sum()


def test_dc_bin_is_the_sum_of_the_resized_beam_and_power_below_bin_60_is_ignored():
    power = np.zeros((400, 3768), np.float32)
    power[:, :60] = 1.0  # near-range returns only: suppressed, so every beam is empty
    assert not np.any(beam_fft_features(power))
    power[:, 60:] = 0.5  # flat beyond bin 60: resized beam ~0.5 on all 256 columns but the first few
    f = beam_fft_features(power)
    assert np.allclose(f[:, 0], 0.5 * 256, rtol=0.03)


def test_vocabulary_is_fit_to_convergence_on_every_beam():
    """Two kinds of beam (a near and a far reflector) in the database and k = 2: the converged words are
    the mean |FFT| of each kind, so a database scan's VLAD has zero residual (after the signed root, the
    descriptor of a scan made of one kind only is all zero in the other word)."""
    near = np.zeros((400, 3768), np.float32)
    near[:, 500:520] = 1.0
    far = np.zeros((400, 3768), np.float32)
    far[:, 3000:3020] = 1.0
    m = RadVLAD(RadVLADConfig(num_clusters=2))
    db = [m.prepare(_scan(near)), m.prepare(_scan(far))]
    m.fit(db)
    words = sorted(m.centres.tolist(), key=lambda c: c[1])
    means = sorted([db[0]["beams"].mean(0).tolist(), db[1]["beams"].mean(0).tolist()], key=lambda c: c[1])
    assert np.allclose(words, means, rtol=1e-4, atol=1e-3)
