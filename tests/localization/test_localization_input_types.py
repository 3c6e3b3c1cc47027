"""QA session 37: a RadarScan (or None) handed where the scan's features belong, or a path / array where a RadarScan
belongs, ended in an AttributeError deep inside; now the library's own error says what to pass."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.errors import ConfigError
from reradar_core.io.scan import RadarScan
from reradar_core.localization import InMemoryKeyframes, Localizer
from reradar_core.retrieval import GlobalIndex


def _scan() -> RadarScan:
    return RadarScan(np.zeros((400, 100), np.float32), np.linspace(0, 2 * np.pi, 400, endpoint=False),
                     np.zeros(400, np.int64), 0.0438, 0.0)


def test_localize_takes_scan_features_and_says_so() -> None:
    loc = Localizer(GlobalIndex(np.eye(2, 4, dtype=np.float32)), InMemoryKeyframes(lambda i: None, np.zeros((2, 3))))  # type: ignore[arg-type,return-value]
    for wrong in (_scan(), None, "scan.png"):
        with pytest.raises(ConfigError, match="takes a scan's ScanFeatures.*describe"):
            loc.localize(wrong)  # type: ignore[arg-type]


def test_describe_takes_a_radar_scan_and_says_so() -> None:
    from reradar_core.model import DescriptorExtractor

    ex = DescriptorExtractor.from_pretrained()
    for wrong in (None, np.zeros((400, 100)), "scan.png"):
        with pytest.raises(ConfigError, match="takes a RadarScan.*load_scan"):
            ex.describe(wrong)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="describe_batch takes a RadarScan"):
        ex.describe_batch([_scan(), None])  # type: ignore[list-item]


# ---- QA session 38: library calls that gave silent wrong answers or failed deep inside


def _features(rng: np.random.Generator, g: np.ndarray, channels: int = 8, n: int = 40):
    from reradar_core.features import ScanFeatures

    local = rng.normal(size=(n, channels))
    return ScanFeatures(g, rng.uniform(-50, 50, (n, 2)), local / np.linalg.norm(local, axis=1, keepdims=True), 0)


def _small_localizer(config=None) -> Localizer:
    rng = np.random.default_rng(0)
    kfs = [_features(rng, np.eye(4)[i]) for i in range(2)]
    return Localizer(GlobalIndex(np.eye(2, 4, dtype=np.float32)), InMemoryKeyframes(kfs, np.zeros((2, 3))), config)


def test_keyframe_headings_in_degrees_and_short_timestamps_are_refused() -> None:
    rng = np.random.default_rng(1)
    kfs = [_features(rng, np.eye(4)[i % 4]) for i in range(40)]
    straight_deg = np.c_[np.zeros(40), np.arange(40) * 3.0, np.full(40, 90.0)]  # a drive north, yaw in degrees
    with pytest.raises(ConfigError, match="look like degrees"):
        InMemoryKeyframes(kfs, straight_deg)
    with pytest.raises(ConfigError, match="5 keyframe timestamps for 40 poses"):
        InMemoryKeyframes(kfs, np.c_[np.zeros(40), np.arange(40) * 3.0, np.full(40, np.pi / 2)], np.arange(5))


def test_a_call_with_other_alignment_settings_is_refused() -> None:
    from dataclasses import replace

    from reradar_core.localization import LocalizationConfig
    from reradar_core.matching import AlignmentConfig

    loc = _small_localizer()
    q = _features(np.random.default_rng(2), np.eye(4)[0])
    other = replace(LocalizationConfig(), alignment=AlignmentConfig(score_threshold_m=3.0))
    with pytest.raises(ConfigError, match="alignment settings differ from the Localizer's"):
        loc.localize(q, other)
    # the same alignment with other retrieval settings is a call's own business
    assert loc.localize(q, replace(LocalizationConfig(), top_k=1)).status in ("localized", "not_localized")


def test_query_local_descriptors_of_another_model_are_named() -> None:
    loc = _small_localizer()
    q = _features(np.random.default_rng(3), np.eye(4)[0], channels=16)
    with pytest.raises(ConfigError, match="16 values but the map's have 8"):
        loc.localize(q)


def test_scan_features_normalise_a_scaled_descriptor_and_refuse_transposed_keypoints() -> None:
    from reradar_core.features import ScanFeatures

    f = ScanFeatures(np.full(4, 5.0), np.zeros((3, 2)), np.ones((3, 2)), 0)
    np.testing.assert_allclose(f.global_descriptor, 0.5)
    unit = np.array([0.6, 0.8, 0.0, 0.0], np.float32)
    assert ScanFeatures(unit, np.zeros((0, 2)), np.zeros((0, 2)), 0).global_descriptor is not None
    np.testing.assert_array_equal(ScanFeatures(unit, np.zeros((0, 2)), np.zeros((0, 2))).global_descriptor, unit)
    with pytest.raises(ValueError, match="non-zero"):
        ScanFeatures(np.zeros(4), np.zeros((3, 2)), np.ones((3, 2)), 0)
    with pytest.raises(ValueError, match=r"keypoints_xy_m must be \(N, 2\)"):
        ScanFeatures(unit, np.zeros((2, 3)), np.ones((3, 2)), 0)


def test_whole_number_settings_and_prior_sigmas_are_checked_when_made() -> None:
    from reradar_core.localization import LocalizationConfig, PosePrior

    with pytest.raises(ConfigError, match="top_k must be a whole number, got 2.5"):
        LocalizationConfig(top_k=2.5)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="sigma_xy_m must be a number"):
        PosePrior(np.zeros(3), sigma_xy_m="2", sigma_yaw_rad=0.1)  # type: ignore[arg-type]
