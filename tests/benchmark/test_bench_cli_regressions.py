"""`reradar bench` on folders: one result per query folder, repeated methods, a re-used --out, pose-time units,
presets of suites and of recorded folders, console wording (QA findings 1-4, 9, 12, 16)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from reradar_core.benchmark.cli import _every_text, unique_methods
from reradar_core.benchmark.results import signed_points
from reradar_core.benchmark.suites import pairs_from_folders, query_pair_names
from reradar_core.benchmark.synthetic import loop_poses, synthetic_world, write_synthetic_sequence
from reradar_core.errors import ConfigError, DatasetError, PoseFileError
from reradar_core.io.datasets import check_pose_time_unit, load_sequence, write_sequence_meta
from reradar_core.io.poses import PoseSequence

FAST = ["--no-timing", "--no-yaw-curve", "--no-rotation", "--no-plots"]


def _bench(args: list[str]):
    from reradar_cli import app

    return CliRunner().invoke(app, ["bench", *args])


def test_query_names_are_unique_per_folder(tmp_path):
    """QA 1: data/alt2/q and data/alt/q both became 'q' in results.json (the last one won)."""
    db, a, b = tmp_path / "db", tmp_path / "alt" / "q", tmp_path / "alt2" / "q"
    assert query_pair_names(db, [a, b]) == ["alt-q", "alt2-q"]
    assert query_pair_names(db, [a, tmp_path / "other"]) == ["q", "other"]
    assert query_pair_names(tmp_path / "x" / "q", [a]) == ["q-query"]
    with pytest.raises(ConfigError, match="names the same folder as --query"):
        query_pair_names(db, [a, tmp_path / "alt" / ".." / "alt" / "q"])


def test_bench_keeps_every_query_folder_runs_each_method_once_and_clears_old_arrays(loop_sequences, tmp_path,
                                                                                   cache_env):
    """QA 1, 3, 4, 16: two query folders named q; --methods ringkey,ringkey crashed; a re-used --out kept the
    per-query arrays of the earlier run."""
    _, db, q = loop_sequences
    for parent in ("alt", "alt2"):
        shutil.copytree(q.root, tmp_path / parent / "q")
    out = tmp_path / "out"
    stale = out / "per_query" / "old-split" / "raplace.npz"
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"old")
    mine = out / "per_query" / "notes.txt"
    mine.write_text("not the bench's")
    r = _bench(["--database", str(db.root), "--query", str(tmp_path / "alt" / "q"), "--query",
                str(tmp_path / "alt2" / "q"), "--preset", "boreas", "--methods", "ringkey,RingKey", "--limit", "4", *FAST,
                "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "names RingKey more than once; each runs once" in r.output
    assert "alt-q: database sequence 'db-run' (4 scans), query sequence 'q' (4 scans)" in r.output
    res = json.loads((out / "results.json").read_text())
    assert list(res["sequences"]) == ["alt-q", "alt2-q"] and res["settings"]["methods"] == ["ringkey"]
    assert res["settings"]["pairs"]["alt2-q"]["query_folder"].endswith("alt2/q")
    assert sorted(p.relative_to(out / "per_query").as_posix() for p in (out / "per_query").rglob("*")
                  if p.is_file()) == ["alt-q/ringkey.npz", "alt2-q/ringkey.npz", "notes.txt"]
    # both instants, each named (QA session 24: query_xy is the first-azimuth position, est_pose mid-sweep)
    with np.load(out / "per_query" / "alt-q" / "ringkey.npz") as z:
        qseq = load_sequence(tmp_path / "alt" / "q", preset="boreas")
        d = np.linalg.norm(z["query_xy"][:, None] - qseq.poses.poses[None, :, :2], axis=2)
        rows = d.argmin(axis=1)  # the scans --limit kept
        assert len(rows) == 4 and np.all(d.min(axis=1) < 1e-9)
        np.testing.assert_allclose(z["query_pose_mid_sweep"], qseq.mid_sweep_poses()[rows])
    # the same folder twice is refused before anything runs
    r = _bench(["--database", str(db.root), "--query", str(q.root), "--query", str(q.root), "--preset", "boreas",
                *FAST, "--out", str(tmp_path / "out2")])
    assert r.exit_code == 2 and "names the same folder as --query" in r.output


def test_method_and_wording_helpers():
    """QA 3, 16: duplicate methods dropped in order; 'every 2nd scan'; no '-0.00' in the rotation table."""
    assert unique_methods(["raplace", "ringkey", " RaPlace"]) == (["raplace", "ringkey"], [" RaPlace"])
    assert [_every_text(k) for k in (1, 2, 3, 4, 11, 12, 13, 21, 22)] == [
        "every scan", "every 2nd scan", "every 3rd scan", "every 4th scan", "every 11th scan", "every 12th scan",
        "every 13th scan", "every 21st scan", "every 22nd scan"]
    assert [signed_points(v) for v in (-0.0, 0.0, -0.001, 0.004, 1.5, -2.25)] == [
        "0.00", "0.00", "0.00", "0.00", "+1.50", "-2.25"]


def test_bench_refuses_a_preset_with_a_suite(tmp_path, cache_env):
    """QA 9: --suite smoke --preset oxford silently ignored --preset."""
    r = _bench(["--suite", "smoke", "--preset", "oxford", *FAST, "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "--preset is for folders" in " ".join(r.output.split())


def test_a_query_recorded_with_another_radar_names_both_recordings(loop_sequences, tmp_path):
    """QA 12: without --preset the message spoke of a preset 'passed' and printed '+0%' for 0.2 %."""
    _, db, q = loop_sequences
    shutil.copytree(q.root, tmp_path / "q_mulran")
    write_sequence_meta(tmp_path / "q_mulran", {"preset": "mulran"})
    shutil.copytree(db.root, tmp_path / "db-run")  # a Boreas folder names its preset (session 24: never the default)
    write_sequence_meta(tmp_path / "db-run", {"preset": "boreas"})
    with pytest.raises(ConfigError, match=r"database .*db-run was recorded with radar preset 'boreas' and the query "
                                          r".*q_mulran with 'mulran'.*\+0\.2 %.*read at 99\.86 m"):
        pairs_from_folders(tmp_path / "db-run", [tmp_path / "q_mulran"])


@pytest.fixture(scope="module")
def relative_us(tmp_path_factory) -> Path:
    """A Boreas-layout folder of 8 scans whose pose file holds relative µs times (a render without its
    reradar_sim.json): 8 poses on a 60 m circle, 0.25 s apart."""
    root = tmp_path_factory.mktemp("rel") / "rel"
    with pytest.raises(PoseFileError, match="ambiguous"):
        write_synthetic_sequence(root, synthetic_world(seed=5), loop_poses(8), seed=1, t0_us=0)
    return root


@pytest.mark.parametrize("unit", ["s", "ms"])
def test_pose_times_read_in_a_unit_1000x_too_coarse_are_refused(relative_us, unit):
    """QA 2: --time-unit s on relative µs placed every scan on the drive's first metres (Recall@1 100 %)."""
    with pytest.raises(DatasetError, match=rf"read as {unit} span .* every scan would be placed on .*pass "
                                           r"--time-unit us"):
        load_sequence(relative_us, preset="boreas", pose_time_unit=unit)
    seq = load_sequence(relative_us, preset="boreas", pose_time_unit="us")
    assert seq.poses.path_length_m() > 250.0


def test_pose_times_read_in_a_unit_too_fine_are_refused_naming_the_unit():
    """The other direction: a pose file in s read as ms is 1000x shorter than the scans; the unit is named."""
    stamps = np.arange(8, dtype=np.int64) * 250_000
    track = PoseSequence(stamps // 1000, loop_poses(8)[:, :2], loop_poses(8)[:, 2])  # 's' read as 'ms'
    with pytest.raises(DatasetError, match="read as ms span 0.00175 s.*pass --time-unit s$"):
        check_pose_time_unit(track, stamps, "ms", "poses.csv")


def test_a_crop_of_a_long_drive_is_not_taken_for_a_unit_error():
    """A folder holding 10 scans of an hour's drive (one pose per scan, as Boreas) passes; so does a pose file
    sampled 50x faster than the scans."""
    t = np.arange(14_400, dtype=np.int64) * 250_000
    xy = np.column_stack([np.arange(14_400) * 2.5, np.zeros(14_400)])
    track = PoseSequence(t, xy, np.zeros(14_400))
    check_pose_time_unit(track, t[5000:5010], "us", "poses.csv")
    fast = np.arange(50 * 40, dtype=np.int64) * 5_000
    check_pose_time_unit(PoseSequence(fast, np.column_stack([fast / 1e5, 0 * fast]), 0 * fast),
                         fast[::50][:40], "us", "poses.csv")


def test_a_query_that_does_not_name_its_radar_is_not_read_with_the_databases(loop_sequences, tmp_path):
    """QA session 36: a Boreas-layout query folder without its render's record was read with the database's preset
    (boreas-2021 scans as boreas: Recall@1 5 %, no word); it must name its radar, as such a database must."""
    from reradar_core.io.datasets import SIM_META_FILE

    _, db, q = loop_sequences
    shutil.copytree(q.root, tmp_path / "q_bare")
    (tmp_path / "q_bare" / SIM_META_FILE).unlink(missing_ok=True)
    shutil.copytree(db.root, tmp_path / "db-run")
    write_sequence_meta(tmp_path / "db-run", {"preset": "boreas"})
    with pytest.raises(ConfigError, match=r"q_bare does not say which radar recorded it.*--preset boreas"):
        pairs_from_folders(tmp_path / "db-run", [tmp_path / "q_bare"])
    pairs, _ = pairs_from_folders(tmp_path / "db-run", [tmp_path / "q_bare"], preset="boreas")
    assert len(pairs) == 1 and pairs[0].query.preset.name == "boreas"


@pytest.mark.parametrize("args, message", [(["-m", ""], "--methods names no method"),
                                           (["-m", "ringkey", "--seed", "-1"], "--seed"),
                                           (["--suite", "smoke", "--time-unit", "s", "-m", "ringkey"],
                                            "--time-unit is for folders")])
def test_bench_refuses_empty_methods_a_negative_seed_and_names_what_was_given(args, message, loop_sequences, tmp_path,
                                                                                cache_env):
    """QA session 36: `-m ''` ran all 15 methods, `--seed -1` crashed after every feature was computed, and
    `--suite --time-unit` was told "--query and --time-unit are for folders"."""
    _, db, q = loop_sequences
    where = [] if "--suite" in args else ["--database", str(db.root), "--query", str(q.root), "--preset", "boreas"]
    r = _bench([*where, *args, *FAST, "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and message in " ".join(r.output.split()), r.output
    assert "Traceback" not in r.output


def test_no_method_is_bold_when_all_tie():
    from reradar_core.benchmark.results import _best

    rows = {"a": {"recall@1_all": 0.0}, "b": {"recall@1_all": 0.0}}
    assert _best(rows, "recall@1_all") == set()
    assert _best({"a": {"sr": 90.0}, "b": {"sr": 80.0}}, "sr") == {"a"}
    assert _best({"a": {"sr": 90.0}}, "sr") == {"a"}


@pytest.mark.parametrize("inside", ["database", "query"])
def test_bench_refuses_an_out_folder_inside_a_scan_folder(inside, loop_sequences, tmp_path, cache_env):
    """QA session 36 (left open there): `--out` inside the database or a query folder was accepted, so results.json,
    plots and per_query/ were written among the scans. Refused up front, before any feature is computed; nothing is
    created there."""
    _, db, q = loop_sequences
    folder = Path(db.root if inside == "database" else q.root)
    before = sorted(p.name for p in folder.iterdir())
    r = _bench(["--database", str(db.root), "--query", str(q.root), "--preset", "boreas", "-m", "ringkey", *FAST,
                "--out", str(folder / "results")])
    assert r.exit_code == 2, r.output
    text = " ".join(r.output.replace("│", " ").split())
    assert f"is inside the --{inside} folder" in text and "choose a folder outside" in text, r.output
    assert sorted(p.name for p in folder.iterdir()) == before
