"""QA session 38: pose sequences and bare polar arrays that were read into silently wrong scans or trajectories."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.errors import PoseFileError, ScanFormatError
from reradar_core.io.poses import PoseSequence
from reradar_core.io.scan import RadarScan


def test_pose_sequence_refuses_transposed_positions_and_fractional_times() -> None:
    with pytest.raises(PoseFileError, match=r"\(N, 2\)"):
        PoseSequence(np.arange(5), np.zeros((2, 5)), np.zeros(5))
    with pytest.raises(PoseFileError, match="whole microseconds"):
        PoseSequence(np.array([0.0, 0.5, 1.0]), np.zeros((3, 2)), np.zeros(3))
    whole = PoseSequence(np.array([0.0, 1e6, 2e6]), np.c_[[0.0, 1.0, 2.0], [0.0, 0.0, 0.0]], np.zeros(3))
    assert whole.timestamps_us.tolist() == [0, 1_000_000, 2_000_000]


def test_pose_sequence_out_of_time_order_is_interpolated_only_once_sorted() -> None:
    ps = PoseSequence(np.array([0, 2, 1]), np.c_[[0.0, 8.0, 6.0], [0.0, 0.0, 0.0]], np.zeros(3))
    with pytest.raises(PoseFileError, match="not in time order"):
        ps.interpolate(1)
    assert ps.sorted().interpolate(1)[0] == pytest.approx(6.0)


def test_from_power_scales_any_8_bit_integers_and_refuses_a_transposed_array() -> None:
    power = np.full((400, 3360), 51, np.int64)
    np.testing.assert_allclose(RadarScan.from_power(power, "boreas").power, 0.2)
    with pytest.raises(ScanFormatError, match="8-bit"):
        RadarScan.from_power(np.full((400, 3360), 4095, np.int64), "boreas")
    with pytest.raises(ScanFormatError, match="looks transposed"):
        RadarScan.from_power(np.zeros((3360, 400), np.float32), "boreas")


def test_range_offset_must_be_finite() -> None:
    with pytest.raises(ScanFormatError, match="range offset"):
        RadarScan(np.zeros((4, 10)), np.arange(4) * np.pi / 2, np.zeros(4), 0.04, float("nan"))
