"""Single-session split (the paper's MulRan protocol), --every default, revisit-aware results, progress bar."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from reradar_core.baselines import make_method
from reradar_core.benchmark.runner import BenchConfig, BenchPair, run_benchmark, total_steps
from reradar_core.benchmark.suites import parse_split, split_index, split_pair
from reradar_core.benchmark.synthetic import loop_poses, synthetic_world, write_synthetic_sequence
from reradar_core.errors import ConfigError

T0 = 1_600_000_000_000_000


@pytest.fixture(scope="module")
def one_session(tmp_path_factory):
    """One drive: a 12-pose loop driven twice, then 8 poses far away (no database scan within 20 m).

    Split at scan 12: database = lap 1; queries = lap 2 (12 revisits) + the 8 far poses (no match), driven to
    30 s after lap 2 (a 0.25 s step of 550 m is refused as a position glitch)."""
    lap = loop_poses(12)
    far = np.column_stack([np.linspace(400.0, 540.0, 8), np.full(8, 400.0), np.zeros(8)])
    poses = np.vstack([lap, lap, far])
    stamps = T0 + np.r_[np.arange(24) * 250_000, 36_000_000 + np.arange(8) * 250_000]
    root = tmp_path_factory.mktemp("session")
    return write_synthetic_sequence(root / "drive", synthetic_world(seed=5), poses, seed=3, t0_us=T0,
                                    stamps_us=stamps)


def test_parse_split_forms_and_errors():
    assert (parse_split("765").kind, parse_split("765").value) == ("index", 765)
    assert (parse_split("120s").kind, parse_split("120.5s").value) == ("seconds", 120.5)
    assert (parse_split("t=1566535872045000").kind, parse_split("t=1566535872045000").value) == (
        "timestamp", 1566535872045000)
    for bad in ("abc", "-3", "12us", "t=1.5", "-1s", ""):
        with pytest.raises(ConfigError, match="split-at"):
            parse_split(bad)


def test_split_index_by_index_seconds_and_timestamp(one_session):
    seq = one_session  # 32 scans, 0.25 s apart
    assert split_index(seq, parse_split("12")) == 12
    assert split_index(seq, parse_split("3s")) == 12  # 3.0 s after the first scan = scan 12 exactly
    assert split_index(seq, parse_split("2.9s")) == 12  # first scan at or after 2.9 s
    assert split_index(seq, parse_split(f"t={T0 + 3_000_000}")) == 12
    for empty_side in ("0", "32", "100s", f"t={T0 - 1}"):
        with pytest.raises(ConfigError, match="must both be non-empty"):
            split_index(seq, parse_split(empty_side))


def test_split_pair_takes_before_and_after_then_subsamples(one_session):
    pair = split_pair(one_session, parse_split("12"), every=1)
    np.testing.assert_array_equal(pair.database.timestamps_us, one_session.timestamps_us[:12])
    np.testing.assert_array_equal(pair.query.timestamps_us, one_session.timestamps_us[12:])
    assert pair.split["index"] == 12 and pair.split["timestamp_us"] == T0 + 3_000_000
    every2 = split_pair(one_session, parse_split("12"), every=2)
    # the split is on the full sequence; each half is subsampled from its own start
    np.testing.assert_array_equal(every2.database.timestamps_us, one_session.timestamps_us[0:12:2])
    np.testing.assert_array_equal(every2.query.timestamps_us, one_session.timestamps_us[12::2])


def test_run_single_session_reports_revisit_and_no_match_queries(one_session, tmp_path):
    pair = split_pair(one_session, parse_split("12"))
    methods = [make_method("raplace"), make_method("ringkey")]
    cfg = BenchConfig(radius_m=20.0, cache_root=tmp_path / "features", progress=False, rotation_stress=False)
    res = run_benchmark([pair], methods, tmp_path / "out", cfg, suite="split")
    rows = res["sequences"]["drive@12"]
    for name, r in rows.items():
        assert (r["n_queries"], r["n_revisit"], r["n_no_match"]) == (20, 12, 8), name
        # the same correct answers counted over revisits (headline) and over all queries (the paper's GT)
        assert r["recall@1_all"] == pytest.approx(r["recall@1"] * 12 / 20), name
        # retrieval-only baselines never reject: rejection figures not applicable
        assert r["rejection"] is None and r["correct_rejection_pct"] is None, name
    # lap 2 passes exactly the poses of lap 1: the Radon descriptor finds them
    assert rows["raplace"]["recall@1"] >= 90.0
    assert res["settings"]["pairs"]["drive@12"]["split"]["index"] == 12


def test_overall_progress_bar_counts_every_step(one_session, tmp_path, monkeypatch):
    from reradar_core.benchmark import runner

    bars = []

    class Recorder(runner.tqdm):  # type: ignore[misc, valid-type]
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            bars.append((k.get("desc"), k.get("disable", False), self))

    monkeypatch.setattr(runner, "tqdm", Recorder)
    pair = split_pair(one_session, parse_split("12"))
    cfg = BenchConfig(radius_m=20.0, cache_root=tmp_path / "features", progress=True, rotation_limit=5)
    methods = [make_method("ringkey"), make_method("radvlad")]
    # database 12 scans x 2 methods, queries 20 x 2 features + 20 x 2 answers, rotation 5 x 2 x 3
    assert total_steps([pair], 2, cfg) == 12 * 2 + 2 * 20 * 2 + 3 * 5 * 2
    run_benchmark([pair], methods, tmp_path / "out", cfg)
    overall = [b for desc, _, b in bars if desc == "bench"]
    assert len(overall) == 1 and overall[0].total == 134 and overall[0].n == 134
    # no other bar was shown while the overall one ran
    assert all(disabled for desc, disabled, _ in bars if desc != "bench")


def test_cli_split_at_on_a_folder_uses_every_scan_by_default(one_session, tmp_path, cache_env):
    from reradar_cli import app

    out = tmp_path / "bench-split"
    r = CliRunner().invoke(app, ["bench", "--database", str(one_session.root), "--split-at", "3s",
                                 "--preset", "boreas", "--methods", "ringkey", "--no-timing", "--no-yaw-curve",
                                 "--no-rotation", "--no-plots", "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "frame spacing: every 1 scan(s) of the folders (default 1" in r.output
    assert "split of drive at scan 12 of 32" in r.output
    res = json.loads((out / "results.json").read_text())
    assert res["settings"]["every"] == 1 and res["settings"]["split_at"] == "3s"
    row = res["sequences"]["drive@12"]["ringkey"]
    assert (row["n_queries"], row["n_revisit"], row["n_no_match"]) == (20, 12, 8)
    md = (out / "results.md").read_text()
    assert "Recall@1 and SR are over the revisit queries" in md
    assert "12 revisit queries, 8 without a database keyframe within 20.0 m" in md
    assert "cut at `--split-at 3s` = scan index 12" in md
    assert "correct rejection (%)" in md and "`not_localized`" in md
    # a split takes both halves from one sequence; a query folder with it is refused with a clear message
    bad = CliRunner().invoke(app, ["bench", "--database", str(one_session.root), "--query", str(one_session.root),
                                   "--split-at", "12", "--preset", "boreas", "--out", str(tmp_path / "x")])
    assert bad.exit_code == 2 and "without --query" in bad.output
    bad = CliRunner().invoke(app, ["bench", "--database", str(one_session.root), "--split-at", "40", "--preset", "boreas",
                                   "--out", str(tmp_path / "x")])
    assert bad.exit_code == 2 and "must both be non-empty" in bad.output


def test_pairs_without_split_keep_separate_runs(one_session):
    pair = BenchPair("q", one_session, one_session)
    assert pair.split is None


def test_a_suite_sequence_can_be_split(tmp_path, monkeypatch):
    from reradar_core.benchmark.suites import pairs_from_suite

    monkeypatch.setenv("RERADAR_CACHE_DIR", str(tmp_path / "cache"))
    pairs, radius = pairs_from_suite("smoke", split_at="8", split_sequence="query", progress=False)
    assert radius == 20.0 and [p.name for p in pairs] == ["query@8"]
    p = pairs[0]
    assert (len(p.database), len(p.query)) == (8, 12)  # the smoke query sequence has 20 scans
    assert p.database.timestamps_us.max() < p.query.timestamps_us.min()
    assert p.split["sequence"] == "query" and p.split["index"] == 8
    # default: the suite's database sequence
    assert pairs_from_suite("smoke", split_at="10", progress=False)[0][0].name == "database@10"
    with pytest.raises(ConfigError, match="not a sequence of suite 'smoke'"):
        pairs_from_suite("smoke", split_at="8", split_sequence="nope", progress=False)
    with pytest.raises(ConfigError, match="needs --split-at"):
        pairs_from_suite("smoke", split_sequence="query", progress=False)


def test_cli_bench_refuses_relative_pose_times_until_the_unit_is_given(tmp_path, cache_env):
    from reradar_cli import app
    from reradar_core.errors import PoseFileError

    # a Boreas-layout folder whose GPSTime starts at 0 µs (no absolute UTC time: the unit cannot be told)
    with pytest.raises(PoseFileError, match="ambiguous"):
        write_synthetic_sequence(tmp_path / "rel", synthetic_world(seed=5), loop_poses(8), seed=1, t0_us=0)
    args = ["bench", "--database", str(tmp_path / "rel"), "--split-at", "4", "--preset", "boreas",
            "--methods", "ringkey", "--no-timing", "--no-yaw-curve", "--rotation-limit", "2",
            "--out", str(tmp_path / "out")]  # plots and rotation stress on: both must cope with no revisit
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 2 and "--time-unit" in r.output
    r = CliRunner().invoke(app, args + ["--time-unit", "us"])
    assert r.exit_code == 0, r.output
    res = json.loads((tmp_path / "out" / "results.json").read_text())
    row = res["sequences"]["rel@4"]["ringkey"]
    # 8 poses on a 60 m circle are 45.9 m apart: no query of the second half has a keyframe within 20 m, so
    # the headline is undefined (null), never a misleading 0, and the all-query Recall@1 is 0
    assert (row["n_queries"], row["n_revisit"], row["n_no_match"]) == (4, 0, 4)
    assert row["recall@1"] is None and row["recall@1_all"] == 0.0
