"""ReFeree as the authors' Python code: detector, free-space descriptors, Euclidean retrieval on raw counts."""

from __future__ import annotations

import numpy as np

from reradar_core.baselines.referee import ReFeree, a_referee, r_referee, referee_features


def _beam_image(pulses: list[tuple[int, int]], n_az: int = 4, n_bins: int = 800) -> np.ndarray:
    """Flat 0.1 floor with pulses of 1.0 over [start, start + width) on every azimuth."""
    p = np.full((n_az, n_bins), 0.1, np.float32)
    for start, width in pulses:
        p[:, start : start + width] = 1.0
    return p


def test_detector_finds_one_feature_per_pulse_at_its_middle_bin_beyond_bin_58():
    """Inside a pulse q >> sigma_q and y ~ q, outside y ~ q = -sigma_q: each pulse is one run, its feature
    is run[len // 2], kept when > 58. Pulses at 40-44 (middle 42) and 56-60 (middle 58) are dropped, 57-61
    (middle 59) is kept; pulses at 300-302 and 304-305, one bin apart, are two runs (301, 305)."""
    rows, bins = referee_features(_beam_image([(40, 5), (56, 5), (200, 5), (300, 3), (304, 2)]))
    assert [sorted(bins[rows == r].tolist()) for r in range(4)] == [[202, 301, 305]] * 4
    rows, bins = referee_features(_beam_image([(57, 5), (200, 5)]))
    assert [sorted(bins[rows == r].tolist()) for r in range(4)] == [[59, 202]] * 4


def test_detector_is_scale_invariant_and_skips_rows_without_noise():
    power = _beam_image([(100, 5), (400, 9)])
    r1, b1 = referee_features(power)
    r2, b2 = referee_features(power * 255.0)
    assert np.array_equal(r1, r2) and np.array_equal(b1, b2)
    power[1] = 0.3  # constant row: no negative q, no noise estimate, no features
    rows, _ = referee_features(power)
    assert 1 not in set(rows.tolist())


def test_r_referee_counts_free_azimuths_per_80_bin_chunk():
    img = np.zeros((16, 240), bool)
    img[[0, 3, 5], [10, 100, 239]] = True
    img[7, 10] = True
    assert np.array_equal(r_referee(img), [16 * 80 - 2, 16 * 80 - 1, 16 * 80 - 1])
    # 250 bins -> 3 chunks by np.array_split: 84, 83, 83 bins
    assert np.array_equal(r_referee(np.zeros((4, 250), bool)), [4 * 84, 4 * 83, 4 * 83])


def test_a_referee_counts_free_bins_in_front_of_the_farthest_feature():
    img = np.zeros((16, 100), bool)
    img[0, [10, 50]] = True  # zeros in row[:50]: 50 bins minus the feature at 10 -> 49
    img[9, 30] = True  # sector 1: 30
    assert np.allclose(a_referee(img), np.array([49.0, 30.0]) / (8 * 100))


def test_retrieval_is_euclidean_on_raw_counts_not_cosine():
    """q = (1000, 1000): a = (2000, 2000) has cosine 1 but is 1,414 away; b = (1010, 990) has cosine
    0.99990 and is 14 away. Euclidean (the reference's KD-tree) picks b, cosine would pick a."""
    m = ReFeree()
    desc = [m.describe_prepared({"ring": np.array(v, float), "sectors": np.ones(4)})
            for v in ([2000.0, 2000.0], [1010.0, 990.0])]
    q = m.describe_prepared({"ring": np.array([1000.0, 1000.0]), "sectors": np.ones(4)})
    d = m.distance(q, m.build_index(desc))
    assert np.allclose(d, [np.sqrt(2) * 1000.0, np.sqrt(200.0)])
    assert int(np.argmin(d)) == 1


def test_heading_is_the_best_circular_sector_shift():
    m = ReFeree()
    sectors = np.zeros(50)
    sectors[[3, 4, 20]] = [1.0, 0.5, 0.8]
    db = m.build_index([m.describe_prepared({"ring": np.ones(3), "sectors": sectors})])
    q = m.describe_prepared({"ring": np.ones(3), "sectors": np.roll(sectors, 5)})  # q[j + 5] = d[j]
    assert np.isclose(m.estimate_heading(q, db, 0), 5 * 2 * np.pi / 50)
