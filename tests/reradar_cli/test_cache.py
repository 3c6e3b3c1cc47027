"""``reradar cache``: parts of the cache folder, their sizes with hard links counted once, and a prune that removes
only what no run reads again (old simulator versions' renders, calibration probe renders)."""

from __future__ import annotations

import os
from pathlib import Path

from typer.testing import CliRunner

from reradar_cli import app
from reradar_core.cli_commands.cache import cache_parts, prune_parts, reclaimable_bytes
from reradar_core.sim.writer import SIM_VERSION

KB64 = 64 * 1024


def _file(path: Path, size: int = KB64) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(os.urandom(size))
    return path


def _cache(root: Path) -> dict[str, Path]:
    old = root / "sim" / "v1" / "suite" / "seq"
    cur = root / "sim" / f"v{SIM_VERSION}" / "suite" / "seq"
    files = {
        "old_only": _file(old / "a.png"),
        "shared": _file(old / "b.png"),
        "current": _file(cur / "c.png"),
        "calib": _file(root / "calib" / "probe.npz", 2 * KB64),
        "train": _file(root / "training" / "cartesian" / "k" / "images.npy"),
        "features": _file(root / "bench" / "features" / "m" / "s.h5"),
        "result": _file(root / "bench" / "loop-sim" / "results.json", 100),
        "map": _file(root / "maps" / "city.h5"),
    }
    os.link(files["shared"], cur / "b.png")  # carried over: one file, two versions
    return files


def _by_what(parts):
    return {p.what: p for p in parts}


def test_parts_sizes_and_staleness(tmp_path):
    _cache(tmp_path)
    parts = _by_what(cache_parts(tmp_path))
    old, cur = parts["simulator v1 renders"], parts[f"simulator v{SIM_VERSION} renders"]
    assert old.stale and not cur.stale and parts["calibration probe renders"].stale
    assert not parts["training images (Cartesian crops)"].stale and not parts["benchmark feature caches"].stale
    assert "benchmark and training results (1 folders)" in parts
    assert not parts["the service's registered maps (RERADAR_MAPS_DIR default)"].stale
    # disk usage: two 64 KiB files in each simulator version (one of them the same inode)
    assert old.size_bytes >= 2 * KB64 and cur.size_bytes >= 2 * KB64
    # a prune frees the old version's own file and the probe renders, not the file the current version links to
    reclaim = reclaimable_bytes(list(parts.values()))
    assert 3 * KB64 <= reclaim < 4 * KB64


def test_listing_changes_nothing_and_prune_keeps_what_runs_read(tmp_path, monkeypatch):
    files = _cache(tmp_path)
    monkeypatch.setenv("RERADAR_CACHE_DIR", str(tmp_path))
    runner = CliRunner()
    res = runner.invoke(app, ["cache"])
    assert res.exit_code == 0, res.output
    assert "simulator v1 renders" in res.output and "--prune" in res.output
    assert all(p.exists() for p in files.values())
    shared = files["shared"].read_bytes()
    res = runner.invoke(app, ["cache", "--prune"])
    assert res.exit_code == 0, res.output
    assert not (tmp_path / "sim" / "v1").exists() and not (tmp_path / "calib").exists()
    for kept in ("current", "train", "features", "result", "map"):
        assert files[kept].exists()
    assert (tmp_path / "sim" / f"v{SIM_VERSION}" / "suite" / "seq" / "b.png").read_bytes() == shared
    res = runner.invoke(app, ["cache"])
    assert "nothing stale" in res.output


def test_prune_parts_removes_only_stale(tmp_path):
    _cache(tmp_path)
    removed = prune_parts(cache_parts(tmp_path))
    assert sorted(p.name for p in removed) == ["calib", "v1"]
