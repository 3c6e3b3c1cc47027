"""``reradar cache``: parts of the cache folder, their sizes with hard links counted once, and a prune that removes
only what no run reads again (old simulator versions' renders, calibration probe renders, training images and
feature caches whose source folder is gone)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
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
        "calib": _file(root / "calib" / "loop-sim-hard-0123456789abcdef.npz", 2 * KB64),
        "train": _file(root / "training" / "cartesian" / "k" / "images.npy"),
        "features": _file(root / "bench" / "features" / "m" / "s.h5"),
        "result": _file(root / "bench" / "loop-sim" / "results.json", 100),
        "map": _file(root / "maps" / "city.h5"),
    }
    os.link(files["shared"], cur / "b.png")  # carried over: one file, two versions
    for seq in (old, cur):
        (seq / ".reradar_render_version").write_text(f"{SIM_VERSION}\n")  # what the simulator's writer leaves
    return files


def _by_what(parts):
    return {p.what: p for p in parts}


def test_parts_sizes_and_staleness(tmp_path):
    _cache(tmp_path)
    parts = _by_what(cache_parts(tmp_path))
    old, cur = parts["simulator v1 renders"], parts[f"simulator v{SIM_VERSION} renders"]
    assert old.stale and not cur.stale and parts["calibration probe renders"].stale
    assert not parts["training images (Cartesian crops) (1)"].stale and not parts["benchmark feature caches (1)"].stale
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


def test_derived_caches_of_folders_that_are_gone_are_stale(tmp_path, monkeypatch):
    import json

    import h5py

    from reradar_core.paths import CACHE_SOURCE_ATTR, CACHE_SOURCE_FILE

    cache, data = tmp_path / "cache", tmp_path / "data"
    (data / "seq-here").mkdir(parents=True)
    cart = cache / "training" / "cartesian"
    for key, src in (("live", data / "seq-here"), ("gone", data / "seq-gone"), ("legacy", None)):
        _file(cart / key / "images.npy")
        if src is not None:
            (cart / key / CACHE_SOURCE_FILE).write_text(json.dumps({"root": str(src)}))
    feats = cache / "bench" / "features" / "ringkey-abc-a2"
    feats.mkdir(parents=True)
    for name, src in (("here.h5", data / "seq-here"), ("gone.h5", data / "seq-gone"), ("legacy.h5", None)):
        with h5py.File(feats / name, "w") as f:
            f.create_dataset("x", data=np.zeros(KB64 // 8))
            if src is not None:
                f.attrs[CACHE_SOURCE_ATTR] = str(src)
    parts = _by_what(cache_parts(cache))
    stale_imgs = parts["training images (Cartesian crops) of folders that no longer exist (1)"]
    stale_feats = parts["benchmark feature caches of folders that no longer exist (1)"]
    assert stale_imgs.stale and stale_imgs.paths == (cart / "gone",)
    assert stale_feats.stale and stale_feats.paths == (feats / "gone.h5",)
    kept = parts["training images (Cartesian crops) (2)"]
    assert not kept.stale and "1 written before sources were recorded" in kept.why
    assert not parts["benchmark feature caches (2)"].stale
    monkeypatch.setenv("RERADAR_CACHE_DIR", str(cache))
    res = CliRunner().invoke(app, ["cache", "--prune"])
    assert res.exit_code == 0, res.output
    assert not (cart / "gone").exists() and not (feats / "gone.h5").exists()
    assert (cart / "live").is_dir() and (cart / "legacy").is_dir()
    assert (feats / "here.h5").is_file() and (feats / "legacy.h5").is_file()


def test_training_and_bench_caches_record_their_source(tmp_path, monkeypatch):
    import json

    from reradar_core.benchmark.cache import FeatureCache
    from reradar_core.cli_commands.cache import source_of
    from reradar_core.io.datasets import load_sequence, write_sequence_poses, write_sequence_scan
    from reradar_core.io.poses import PoseSequence
    from reradar_core.io.scan import RadarScan
    from reradar_core.paths import CACHE_SOURCE_FILE
    from reradar_core.training.data import cache_sequence

    monkeypatch.setenv("RERADAR_CACHE_DIR", str(tmp_path / "cache"))
    seq_root = tmp_path / "seq"
    ts = 1_600_000_000_000_000 + np.arange(2, dtype=np.int64) * 250_000
    for t in ts:
        write_sequence_scan(seq_root, "boreas", RadarScan.from_power(np.zeros((400, 3360), np.float32), "boreas",
                                                                     start_time_us=int(t)))
    write_sequence_poses(seq_root, "boreas", PoseSequence(ts, np.zeros((2, 2)), np.zeros(2)))
    cache_sequence(load_sequence(seq_root, preset="boreas"), width_px=21, margin_px=2, progress=False)
    (folder,) = (tmp_path / "cache" / "training" / "cartesian").iterdir()
    assert json.loads((folder / CACHE_SOURCE_FILE).read_text()) == {"root": str(seq_root.resolve())}
    assert source_of(folder) == str(seq_root.resolve())
    FeatureCache("m-1", "seq-1", source_root=seq_root).close()
    assert source_of(tmp_path / "cache" / "bench" / "features" / "m-1" / "seq-1.h5") == str(seq_root.resolve())


def test_prune_never_removes_folders_that_only_share_a_name(tmp_path, monkeypatch):
    """QA (session 20): ``RERADAR_CACHE_DIR`` pointed at a project folder, or left empty (the current folder), made
    ``--prune`` remove that folder's own ``calib/`` and ``sim/v3/``, judged by their names alone."""
    project = tmp_path / "project"
    own = [_file(project / "calib" / "a.yaml", 10), _file(project / "sim" / "v3" / "run.txt", 10),
           _file(project / "sim" / "v4" / "results" / "r.csv", 10)]
    _file(project / "sim" / "v2" / "suite" / "seq" / "a.png", 10)
    (project / "sim" / "v2" / "notes.txt").write_text("mine")  # a render folder with files of its own: kept
    (project / "sim" / "v2" / "suite" / "seq" / ".reradar_render_version").write_text("2\n")
    runner = CliRunner()
    for env in (str(project), ""):
        monkeypatch.setenv("RERADAR_CACHE_DIR", env)
        monkeypatch.chdir(project)
        res = runner.invoke(app, ["cache", "--prune"])
        assert res.exit_code == 0, res.output
        assert all(p.exists() for p in own) and (project / "sim" / "v2" / "notes.txt").exists()
    # the empty variable means the default cache folder, not the current one
    assert str(project / ".cache" / "reradar") in res.output
    parts = _by_what(cache_parts(project))
    assert not any(p.stale for p in parts.values()) and "kept (holds files" in parts["calib"].why


def test_distinct_folder_labels_add_parents_only_where_names_clash(tmp_path):
    """One labelling for sim-report's columns and bench's query names (`reradar_core.paths`)."""
    from reradar_core.paths import distinct_folder_labels

    a, b, c = tmp_path / "a" / "seq", tmp_path / "b" / "seq", tmp_path / "c" / "other"
    for d in (a, b, c):
        d.mkdir(parents=True)
    assert distinct_folder_labels([a, b, c]) == ["a/seq", "b/seq", "other"]
    assert distinct_folder_labels([a, b, c], sep="-") == ["a-seq", "b-seq", "other"]
    twice = distinct_folder_labels([a, a / ".." / "seq"])  # the same folder: one label twice (its whole path)
    assert twice[0] == twice[1] and twice[0].endswith("a/seq")
    deep_a, deep_b = tmp_path / "x" / "run" / "q", tmp_path / "y" / "run" / "q"
    assert distinct_folder_labels([deep_a, deep_b]) == ["x/run/q", "y/run/q"]
