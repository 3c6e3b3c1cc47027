"""Start-up and map registration read their inputs once in the service's process.

- ``reradar serve`` loaded the descriptor model twice (~1 s): once to check RERADAR_MODEL before the server starts,
  once more in the app's lifespan. The check's load is now the served one, handed to ``create_app``.
- ``POST /maps`` with a map file opened the uploaded HDF5 file twice in-process after the child-process probe:
  once to check its metadata before the install, once more to serve it. The checked open file is now served.
"""

from __future__ import annotations

import os
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

import maps.store as store_module
import service.core.registry as registry_module
from reradar_core.errors import MapFormatError
from reradar_core.io.scan import encode_navtech_png_bytes

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import (  # noqa: E402
    API_KEY,
    N_KEYFRAMES,
    count_model_loads,
    keyframe_time,
    make_scan,
    started_app,
    upload_map_file,
)

AUTH = {"X-API-Key": API_KEY}


# ---- 1. reradar serve: one model load per process -------------------------------------------------------------
@pytest.fixture
def serve_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """The environment of a ``reradar serve`` run in this process, restored afterwards; yields its maps dir."""
    from service.core.http_protocol import HEADER_TIMEOUT_ENV, HeadTimeoutH11Protocol

    for var in ("RERADAR_REDIS_URL", "RERADAR_WORKERS", "RERADAR_MODEL", "RERADAR_MAPS_DIR"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("RERADAR_LOAD_DEMO_MAP", "false")
    monkeypatch.setattr(HeadTimeoutH11Protocol, "header_timeout_s", HeadTimeoutH11Protocol.header_timeout_s)
    header_timeout = os.environ.get(HEADER_TIMEOUT_ENV)  # serve sets it for its workers
    yield tmp_path / "maps"
    if header_timeout is None:
        os.environ.pop(HEADER_TIMEOUT_ENV, None)
    else:
        os.environ[HEADER_TIMEOUT_ENV] = header_timeout


def test_serve_loads_the_model_once_and_serves_that_load(serve_env: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """The model is loaded once, as the lifespan loads it (the runtime RERADAR_NETWORK_RUNTIME chooses, at
    RERADAR_TORCH_THREADS threads: an ONNX Runtime session is made at torch's thread count), and that load is
    what the app serves."""
    import torch
    import uvicorn

    from reradar_cli import app

    loads = count_model_loads(monkeypatch)

    served: list[object] = []

    def run_lifespan(app_: Any, **_: Any) -> None:  # instead of a listening server: start up, answer, shut down
        with TestClient(app_) as client:
            assert client.get("/readyz").status_code == 200
            served.append(app_.state.reradar.extractor)

    monkeypatch.setattr(uvicorn, "run", run_lifespan)
    monkeypatch.setenv("RERADAR_TORCH_THREADS", "2")
    threads_before = torch.get_num_threads()
    try:
        res = CliRunner().invoke(app, ["serve", "--maps-dir", str(serve_env)])
    finally:
        torch.set_num_threads(threads_before)
    assert res.exit_code == 0, res.output
    assert len(loads) == 1, loads
    assert loads[0]["runtime"] is None and loads[0]["threads"] == 2  # as the lifespan's own load would be
    assert served == [loads[0]["extractor"]]


def test_serve_with_workers_still_checks_the_model_before_starting(serve_env: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """``--workers N``: the spawned workers load their own model; the supervisor still refuses a bad
    RERADAR_MODEL in one line before anything starts."""
    from reradar_cli import app

    monkeypatch.setenv("RERADAR_MODEL", "nosuch")
    res = CliRunner().invoke(app, ["serve", "--workers", "2", "--maps-dir", str(serve_env)])
    assert res.exit_code == 2 and "RERADAR_MODEL" in res.output and "unknown model 'nosuch'" in res.output


# ---- 2. POST /maps with a map file: one in-process open of the uploaded file -----------------------------------
@pytest.fixture
def h5_opens(monkeypatch: pytest.MonkeyPatch) -> list[Path]:
    """Every HDF5 open of a map file in this process (``maps.store._open_h5``; the probe's child is another)."""
    opened: list[Path] = []
    real_open_h5 = store_module._open_h5

    def counting_open_h5(path: Path) -> Any:
        opened.append(Path(path))
        return real_open_h5(path)

    monkeypatch.setattr(store_module, "_open_h5", counting_open_h5)
    return opened


@pytest.mark.parametrize("share_map_arrays", [True, False], ids=["shared-arrays", "private-keyframes"])
def test_map_file_upload_is_opened_once_in_process_and_served_from_that_open(
        fake_map: Path, tmp_path: Path, h5_opens: list[Path], share_map_arrays: bool) -> None:
    """One open, of the staged file, before the install (so a map the model cannot use is never stored); the
    database reads every keyframe through it after the install (shared arrays or preload) and serves it under
    the installed name."""
    maps_dir = tmp_path / "maps"
    with started_app(maps_dir, share_map_arrays=share_map_arrays) as client:
        r = upload_map_file(client, fake_map, "once")
        assert r.status_code == 201, r.text
        assert len(h5_opens) == 1 and h5_opens[0].parent.name == ".staging", h5_opens
        assert not h5_opens[0].exists()  # the staged name is gone; the open file is the installed one
        entry = client.app.state.reradar.registry.get("once")  # type: ignore[attr-defined]
        assert entry.state == "ready" and len(entry.db) == N_KEYFRAMES
        assert entry.db.map.path == maps_dir.resolve() / "once.h5"  # its messages name the installed file
        assert entry.file_id == registry_module.file_identity(entry.path)
        png = encode_navtech_png_bytes(make_scan(3, keyframe_time(3)))
        r = client.post("/localize", data={"map_id": "once"}, files={"scan": ("s.png", png)}, headers=AUTH)
        assert r.status_code == 200 and r.json()["status"] == "localized", r.text
    assert len(h5_opens) == 1


def test_map_file_refused_after_the_install_is_closed_and_removed(
        fake_map: Path, tmp_path: Path, h5_opens: list[Path], monkeypatch: pytest.MonkeyPatch) -> None:
    """A refusal while the database is set up (after the install, e.g. a shared arrays check) still answers 422
    naming "the uploaded map", removes the installed file and closes the one open file."""
    opened_maps: list[Any] = []

    def refusing_database(kf_map: Any, *args: Any, **kwargs: Any) -> None:
        opened_maps.append(kf_map)
        raise MapFormatError(f"{kf_map.path}: keyframe 2 is damaged (test)")

    monkeypatch.setattr(registry_module, "MapDatabase", refusing_database)
    maps_dir = tmp_path / "maps"
    with started_app(maps_dir) as client:
        r = upload_map_file(client, fake_map, "refused")
        assert r.status_code == 422, r.text
        assert r.json()["detail"] == "the uploaded map: keyframe 2 is damaged (test)"
        assert not (maps_dir / "refused.h5").exists() and not any((maps_dir / ".staging").iterdir())
        assert client.get("/maps/refused").status_code == 404
    assert len(h5_opens) == 1 and len(opened_maps) == 1 and opened_maps[0]._file is None  # closed


def test_map_file_the_model_cannot_use_is_refused_before_the_install(
        fake_map: Path, tmp_path: Path, h5_opens: list[Path]) -> None:
    """The one open is the pre-install check: a map of another model is refused (409) with nothing stored."""
    other = tmp_path / "other.h5"
    shutil.copyfile(fake_map, other)
    with h5py.File(other, "r+") as f:
        f.attrs["weights_sha256"] = "0" * 64
    maps_dir = tmp_path / "maps"
    with started_app(maps_dir) as client:
        r = upload_map_file(client, other, "mismatch")
        assert r.status_code == 409 and "the uploaded map" in r.json()["detail"], r.text
        assert not (maps_dir / "mismatch.h5").exists() and not any((maps_dir / ".staging").iterdir())
    assert len(h5_opens) == 1
