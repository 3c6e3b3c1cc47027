"""Test isolation shared by every test folder."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest


@pytest.fixture(autouse=True)
def _root_log_handlers_restored() -> Iterator[None]:
    """A CLI command run under ``CliRunner`` (``logging.basicConfig``) or the service's log setup adds a handler
    bound to that call's stderr, which the runner closes; a later test's log record then printed "--- Logging error
    ---" with a traceback into another command's output. Each test leaves the root logger's handlers as it found
    them."""
    root = logging.getLogger()
    before, level = list(root.handlers), root.level
    yield
    for handler in [h for h in root.handlers if h not in before]:
        root.removeHandler(handler)
    for handler in before:
        if handler not in root.handlers:
            root.addHandler(handler)
    root.setLevel(level)
