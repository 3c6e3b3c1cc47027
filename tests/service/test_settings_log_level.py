"""RERADAR_LOG_LEVEL takes the words `reradar serve --log-level` takes, in any case (QA, session 25: `debug` was
refused while `--log-level debug` worked)."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from service.core.config import Settings


@pytest.mark.parametrize("given, level", [("debug", "DEBUG"), ("Info", "INFO"), (" warning ", "WARNING"),
                                          ("ERROR", "ERROR")])
def test_log_level_in_any_case(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, given: str, level: str) -> None:
    monkeypatch.setenv("RERADAR_LOG_LEVEL", given)
    assert Settings(maps_dir=tmp_path).log_level == level


def test_an_unknown_log_level_is_still_refused(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("RERADAR_LOG_LEVEL", "verbose")
    with pytest.raises(ValidationError, match="log_level"):
        Settings(maps_dir=tmp_path)
