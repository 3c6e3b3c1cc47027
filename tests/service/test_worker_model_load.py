"""``reradar worker`` loaded the descriptor model twice in one process (~1 s): once to check RERADAR_MODEL before
the worker starts, once more in ``run_worker``. The check's load is now the one the worker builds with, loaded as
``run_worker`` loads it (RERADAR_TORCH_THREADS: an ONNX Runtime session is made at torch's thread count); a bad
RERADAR_MODEL is still one line and exit 2, before the worker starts."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from service_test_fakes import count_model_loads
from typer.testing import CliRunner

import service.cli as cli_module
import service.worker as worker_module


@pytest.fixture
def worker_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[list[dict[str, Any]]]:
    """The environment of a ``reradar worker`` run in this process with Redis taken as reachable and the worker
    itself not started: yields the ``run_worker`` calls (settings, extractor); torch's thread count restored."""
    import torch

    for var in ("RERADAR_MODEL", "RERADAR_WORKERS", "RERADAR_NETWORK_RUNTIME"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("RERADAR_REDIS_URL", "redis://127.0.0.1:6379/0")
    monkeypatch.setenv("RERADAR_MAPS_DIR", str(tmp_path / "maps"))
    monkeypatch.setenv("RERADAR_TORCH_THREADS", "2")
    monkeypatch.setattr(cli_module, "check_redis_credentials_or_exit", lambda settings, unreachable_exit=None: None)
    runs: list[dict[str, Any]] = []

    def fake_run_worker(settings: Any, extractor: Any = None, burst: bool = False) -> None:
        runs.append({"settings": settings, "extractor": extractor})

    monkeypatch.setattr(worker_module, "run_worker", fake_run_worker)
    threads_before = torch.get_num_threads()
    try:
        yield runs
    finally:
        torch.set_num_threads(threads_before)


def test_worker_loads_the_model_once_and_builds_with_that_load(worker_env: list[dict[str, Any]],
                                                                monkeypatch: pytest.MonkeyPatch) -> None:

    from reradar_cli import app

    loads = count_model_loads(monkeypatch)

    res = CliRunner().invoke(app, ["worker"])
    assert res.exit_code == 0, res.output
    assert len(loads) == 1, loads
    assert loads[0]["runtime"] is None and loads[0]["threads"] == 2  # as run_worker's own load would be
    assert len(worker_env) == 1 and worker_env[0]["extractor"] is loads[0]["extractor"]  # built with that load


@pytest.mark.parametrize("model", ["nosuch", "empty.pt"])
def test_worker_refuses_a_bad_model_in_one_line_before_it_starts(worker_env: list[dict[str, Any]], tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch, model: str) -> None:
    from reradar_cli import app

    if model.endswith(".pt"):
        (tmp_path / model).write_bytes(b"")
        model = str(tmp_path / model)
    monkeypatch.setenv("RERADAR_MODEL", model)
    res = CliRunner().invoke(app, ["worker"])
    assert res.exit_code == 2, res.output
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: RERADAR_MODEL: "), res.output
    assert "Traceback" not in res.output
    assert worker_env == []  # the worker never started
