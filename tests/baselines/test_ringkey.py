"""RingKey as the OORD benchmark: bins < 60 ignored, 256 x 256 then 40 x 120 bicubic, mean per ring."""

from __future__ import annotations

import numpy as np

from reradar_core.baselines.ringkey import RingKey, ring_key
from reradar_core.io.scan import RadarScan


def test_ring_key_peaks_at_the_ring_of_a_bright_circle():
    """A full circle at bins 1880..1889 of 3,768: bin 1885 -> column 128.1 of 256 -> ring 60.0 of 120."""
    power = np.zeros((400, 3768), np.float32)
    power[:, 1880:1890] = 1.0
    key = ring_key(power)
    assert key.shape == (120,)
    assert int(np.argmax(key)) == 60
    assert np.all(np.abs(key[:55]) < 0.02 * key.max())  # bicubic ringing stays next to the circle


def test_returns_below_bin_60_are_ignored():
    power = np.zeros((400, 3768), np.float32)
    power[:, 10:60] = 1.0
    assert not np.any(ring_key(power))
    power[:, 60:70] = 1.0  # from bin 60 on they count
    assert ring_key(power).max() > 0


def test_ring_key_is_euclidean_on_the_keys():
    def scan(level: float) -> RadarScan:
        p = np.zeros((400, 3768), np.float32)
        p[:, 1000:1100] = level
        return RadarScan(p, np.arange(400) * 2 * np.pi / 400, np.zeros(400, np.int64), 0.0432)

    m = RingKey()
    keys = [m.describe(scan(v)) for v in (0.2, 0.5, 0.9)]
    d = m.distance(m.describe(scan(0.45)), m.build_index(keys))
    assert np.allclose(d, [np.linalg.norm(keys[i] - m.describe(scan(0.45))) for i in range(3)], rtol=1e-4)
    assert int(np.argmin(d)) == 1
