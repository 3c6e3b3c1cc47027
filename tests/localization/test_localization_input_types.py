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
