"""`reradar bench`: a re-used --out keeps its results until a run completes, per-run odometry refused for two
runs, a database too small for a method refused up front, rejected queries in the trajectory figure, `ours`
as an alias, sequences without revisits, the figure count, help and wording (QA session 24, findings 1, 3,
5, 7-12)."""

from __future__ import annotations

import inspect
import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from reradar_core.benchmark import runner
from reradar_core.benchmark.cli import bench, unique_method_objects
from reradar_core.benchmark.results import results_markdown
from reradar_core.benchmark.runner import (
    PER_QUERY_STAGING_DIR,
    BenchConfig,
    BenchPair,
    min_database_scans,
    run_benchmark,
)
from reradar_core.benchmark.suites import pairs_from_folders
from reradar_core.errors import ConfigError, DatasetError
from reradar_core.io.datasets import write_sequence_meta, write_sequence_poses

FAST = ["--no-timing", "--no-yaw-curve", "--no-rotation", "--no-plots"]


def _bench(args: list[str]):
    from reradar_cli import app

    return CliRunner().invoke(app, ["bench", *args])


def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# ---------------------------------------------------------------- finding 3: a failed run keeps the earlier one
@pytest.mark.parametrize("failure", [DatasetError("scan.png: 3768 range bins, but preset 'boreas' has 3360"),
                                     KeyboardInterrupt()], ids=["error", "interrupt"])
def test_a_failed_or_interrupted_run_keeps_the_earlier_results_and_their_per_query_files(
        loop_sequences, tmp_path, cache_env, monkeypatch, failure):
    """QA 3: a second run into the same --out that failed removed the first run's per_query/*.npz and kept its
    results.json. Now the new arrays wait in a staging folder and replace the old ones only when the run
    completes."""
    _, db, q = loop_sequences
    out = tmp_path / "out"
    args = ["--database", str(db.root), "--query", str(q.root), "--preset", "boreas", "--limit", "4", *FAST,
            "--out", str(out)]
    assert _bench([*args, "--methods", "ringkey"]).exit_code == 0
    before = _files(out)
    assert "per_query/query-run/ringkey.npz" in before

    real = runner.evaluate_method

    def fails_on_ringkey(method, *a, **k):  # raplace's arrays are staged by then
        if method.name == "ringkey":
            raise failure
        return real(method, *a, **k)

    monkeypatch.setattr(runner, "evaluate_method", fails_on_ringkey)
    r = _bench([*args, "--methods", "raplace,ringkey"])
    assert r.exit_code != 0
    assert _files(out) == before  # results.json, results.md and their per-query file, byte for byte
    assert not (out / PER_QUERY_STAGING_DIR).exists()

    # a run that completes replaces the arrays (a staging folder a killed run left is cleared first)
    monkeypatch.setattr(runner, "evaluate_method", real)
    (out / PER_QUERY_STAGING_DIR / "old").mkdir(parents=True)
    r = _bench([*args, "--methods", "raplace"])
    assert r.exit_code == 0, r.output
    after = _files(out)
    assert sorted(k for k in after if k.startswith("per_query/")) == ["per_query/query-run/raplace.npz"]
    assert not (out / PER_QUERY_STAGING_DIR).exists()


def test_run_benchmark_commits_only_when_asked(loop_sequences, tmp_path):
    """``commit=False`` leaves the arrays staged (the CLI commits after its timing and yaw curve); the default
    commits them."""
    _, db, q = loop_sequences
    pair = BenchPair("query-run", db.subset(range(4)), q.subset(range(4)))
    cfg = BenchConfig(radius_m=20.0, cache_root=tmp_path / "features", progress=False, rotation_stress=False)
    run_benchmark([pair], [runner_method("ringkey")], tmp_path / "out", cfg, commit=False)
    assert (tmp_path / "out" / PER_QUERY_STAGING_DIR / "query-run" / "ringkey.npz").is_file()
    assert not (tmp_path / "out" / "per_query").exists()
    assert runner.commit_per_query(tmp_path / "out") == [tmp_path / "out" / "per_query" / "query-run" / "ringkey.npz"]
    assert not (tmp_path / "out" / PER_QUERY_STAGING_DIR).exists()


def runner_method(name: str):
    from reradar_core.baselines import make_method

    return make_method(name)


# ---------------------------------------------------------------- finding 1: per-run odometry, two runs
def _oxford_copy(seq, dest: Path, sim_origin: bool = False) -> Path:
    """``seq``'s scans as an Oxford-layout folder: gt/radar_odometry.csv only (as Oxford / OORD downloads), or
    with the simulator's record of the odometry origin."""
    shutil.copytree(seq.root / "radar", dest / "radar")
    write_sequence_poses(dest, "oxford", seq.poses)
    if sim_origin:
        write_sequence_meta(dest, {"preset": "boreas", "oxford_T_world_origin": [float(v) for v in seq.poses.poses[0]]})
    return dest


def test_two_runs_with_per_run_odometry_are_refused_and_a_split_of_one_runs(loop_sequences, tmp_path, cache_env):
    """QA 1: two Oxford-layout runs (each odometry chain starts at the identity) were put at one origin, 500 m
    apart in truth: 14 'revisits', Recall@1 14 %, correct rejections counted as misses."""
    _, db, q = loop_sequences
    ox_db, ox_q = _oxford_copy(db, tmp_path / "ox-db"), _oxford_copy(q, tmp_path / "ox-q")
    with pytest.raises(ConfigError, match=r"ox-db: its poses come from gt/radar_odometry.csv, odometry that starts "
                                          r"at the identity in every run.*bench one run with --split-at.*"
                                          r"applanix/radar_poses.csv"):
        pairs_from_folders(ox_db, [ox_q], preset="boreas")
    with pytest.raises(ConfigError, match="ox-q: its poses come from gt/radar_odometry.csv"):
        pairs_from_folders(db.root, [ox_q], preset="boreas")  # a map-frame database and an odometry query
    r = _bench(["--database", str(ox_db), "--query", str(ox_q), "--preset", "boreas", "--methods", "ringkey",
                *FAST, "--out", str(tmp_path / "o1")])
    assert r.exit_code == 2 and "Traceback" not in r.output
    assert len([line for line in r.output.splitlines() if line.startswith("error:")]) == 1
    # one run split in two is one frame
    pairs, _ = pairs_from_folders(ox_db, [], preset="boreas", split_at="6")
    assert len(pairs[0].database) == 6 and len(pairs[0].query) == 6
    # renders that record their odometry origin share the simulator's world
    a, b = _oxford_copy(db, tmp_path / "sim-db", True), _oxford_copy(q, tmp_path / "sim-q", True)
    pairs, radius = pairs_from_folders(a, [b])
    np.testing.assert_allclose(pairs[0].query.poses.poses, q.poses.poses, atol=1e-6)
    # the advice works: map-frame poses in applanix/radar_poses.csv beside radar/ (Boreas layout)
    for seq, folder in ((db, ox_db), (q, ox_q)):
        write_sequence_poses(folder, "boreas", seq.poses)
    pairs, _ = pairs_from_folders(ox_db, [ox_q], preset="boreas")
    np.testing.assert_allclose(pairs[0].query.poses.poses, q.poses.poses, atol=1e-6)


# ---------------------------------------------------------------- finding 5: a database too small for a method
def test_resnet18_netvlad_needs_five_database_scans_known_answer(loop_sequences):
    """64 NetVLAD centres on 16 conv5 descriptors per scan (128 px input / 32 = 4 x 4): k-means needs more
    descriptors than centres, i.e. 5 scans; 5 scans calibrate."""
    from reradar_core.baselines.resnet_netvlad import ResNetNetVLAD, ResNetNetVLADConfig

    _, db, _ = loop_sequences
    m = ResNetNetVLAD()
    recs = [m.prepare(db.load_scan(i)) for i in range(5)]
    assert recs[0]["local"].shape[0] == 16
    assert min_database_scans(m) == 5 == 64 // 16 + 1
    assert min_database_scans(ResNetNetVLAD(ResNetNetVLADConfig(num_clusters=32))) == 3
    assert min_database_scans(runner_method("ringkey")) == 1
    m.fit(recs)
    assert np.isfinite(m.alpha) and m.alpha > 0


def test_a_database_too_small_for_a_method_is_refused_before_anything_runs(loop_sequences, tmp_path, cache_env,
                                                                           monkeypatch):
    """QA 5: a 2-scan database aborted the whole bench after the other methods had run, saying 'calibration is
    degenerate (no index gap)'."""
    _, db, q = loop_sequences

    def no_work(*a, **k):
        raise AssertionError("a scan was prepared before the database size was checked")

    monkeypatch.setattr(runner, "prepare_sequence", no_work)
    out = tmp_path / "out"
    r = _bench(["--database", str(db.root), "--split-at", "2", "--preset", "boreas", "--methods",
                "ringkey,resnet18-netvlad", *FAST, "--out", str(out)])
    text = " ".join(r.output.split())
    assert r.exit_code == 2, r.output
    assert ("resnet18-netvlad needs a database of at least 5 scans (it fits its vocabulary on the database), but "
            "database 'db-run' of 'db-run@2' has 2;") in text
    assert "drop resnet18-netvlad from --methods" in text and "index gap" not in text
    assert not (out / "results.json").exists() and not (out / PER_QUERY_STAGING_DIR).exists()


# ---------------------------------------------------------------- finding 7: rejected queries in the figure
def test_trajectory_figure_draws_no_link_for_a_rejected_query(tmp_path, monkeypatch):
    """QA 7: ReRadar's 14 correct rejections were drawn as 14 red 'wrong' links, like RingKey's wrong answers."""
    from reradar_core.benchmark import plots

    drawn: dict[str, int] = {}

    class Recorder(plots.LineCollection):  # type: ignore[misc, valid-type]
        def __init__(self, segments, *a, **k):
            drawn[current[0]] = len(segments)
            super().__init__(segments, *a, **k)

    current = [""]
    monkeypatch.setattr(plots, "LineCollection", Recorder)
    per_query = tmp_path / "per_query"
    q_xy = np.array([[500.0, 0.0], [510.0, 0.0], [520.0, 0.0]])
    db_xy = np.array([[0.0, 0.0], [10.0, 0.0]])
    base = {"recall@1": None, "n_revisit": 0, "f1max": None}
    results = {"sequences": {"far": {"ours": {**base, "rejection": "not_localized"},
                                     "ringkey": {**base, "rejection": None}}}}
    est = {"ours": np.array([[np.nan] * 3, [np.nan] * 3, [509.0, 0.0, 0.0]]), "ringkey": np.full((3, 3), np.nan)}
    for m, e in est.items():
        (per_query / "far").mkdir(parents=True, exist_ok=True)
        np.savez(per_query / "far" / f"{m}.npz", retrieved=np.array([1, 1, 0]), correct=np.zeros(3, bool),
                 positive=np.zeros(3, bool), est_pose=e, query_xy=q_xy, db_xy=db_xy, distance=np.ones(3))
    for m in ("ours", "ringkey"):
        current[0] = m
        plots.plot_trajectory_links(results, per_query, "far", tmp_path / f"{m}.png", methods=[m])
    assert drawn == {"ours": 1, "ringkey": 3}  # ReRadar's two rejected queries have no (red) link
    assert plots.rejected_queries(results["sequences"]["far"]["ours"], est["ours"]).tolist() == [True, True, False]
    # a retrieval-only baseline has no pose either, but it answers every query
    assert not plots.rejected_queries(results["sequences"]["far"]["ringkey"], est["ringkey"]).any()


# ---------------------------------------------------------------- finding 8 and 10: 'ours', the figure count
def test_ours_and_the_default_model_run_once_and_the_row_names_the_model(loop_sequences, tmp_path, cache_env,
                                                                          monkeypatch):
    """QA 8: `--methods ours,our-3-boreas-w05` ran one model twice; the row 'ours' did not name the model.
    QA 10: the closing line counted 2 figures where 3 PNGs were written (the yaw-consistency curve)."""
    from reradar_core.baselines import ours_model_names
    from reradar_core.benchmark import extras
    from reradar_core.benchmark.plots import plot_yaw_consistency
    from reradar_core.model.registry import DEFAULT_MODEL

    if DEFAULT_MODEL not in ours_model_names():
        pytest.skip("the default model is not shipped in this checkout")

    def yaw_stub(results, ours, pair, out_dir, n_scans=4):  # the real curve: 100 network passes, same output
        a = np.arange(0.0, 361.0, 45.0)
        path = plot_yaw_consistency({"x": (a, np.ones_like(a))}, Path(out_dir) / "yaw_consistency.png")
        results.setdefault("figures", []).append(path.name)
        return path

    monkeypatch.setattr(extras, "add_yaw_consistency", yaw_stub)
    _, db, q = loop_sequences
    out = tmp_path / "out"
    r = _bench(["--database", str(db.root), "--query", str(q.root), "--preset", "boreas", "--limit", "3",
                "--methods", f"ours,{DEFAULT_MODEL}", "--no-timing", "--no-rotation", "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert f"note: --methods names one method twice: {DEFAULT_MODEL} is ours (an alias); it runs once" in r.output
    res = json.loads((out / "results.json").read_text())
    assert res["settings"]["methods"] == ["ours"] and res["settings"]["method_models"] == {"ours": DEFAULT_MODEL}
    md = (out / "results.md").read_text()
    assert f"| ours ({DEFAULT_MODEL}) |" in md and f"| {DEFAULT_MODEL} |" not in md
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert sorted(res["figures"]) == pngs and len(pngs) == 3
    assert r.output.rstrip().endswith(f"{out / 'results.md'} and 3 figures")


def test_method_objects_of_one_method_under_two_names_are_one():
    """'netvlad' is resnet18-netvlad; RaPlace and its variant are two methods."""
    kept, dropped = unique_method_objects([runner_method(n) for n in ("netvlad", "raplace", "resnet18-netvlad",
                                                                      "raplace-nodc")])
    assert [m.name for m in kept] == ["resnet18-netvlad", "raplace", "raplace-nodc"]
    assert dropped == [("resnet18-netvlad", "resnet18-netvlad")]


# ---------------------------------------------------------------- finding 9: a sequence without revisits
def test_a_sequence_without_revisits_has_no_f1max_and_logs_no_none_percent(loop_sequences, tmp_path, caplog):
    """QA 9: F1max was a bold 0.00 for every method and the log said 'Recall@1 None%'. Within 0.5 m no query of
    the loop driven 2 m to the side has a database keyframe."""
    from reradar_core.benchmark.plots import make_all_plots

    _, db, q = loop_sequences
    pair = BenchPair("far", db.subset(range(4)), q.subset(range(4)))
    cfg = BenchConfig(radius_m=0.5, cache_root=tmp_path / "features", progress=False, rotation_stress=False)
    with caplog.at_level(logging.INFO, logger="reradar_core.benchmark.runner"):
        res = run_benchmark([pair], [runner_method("ringkey"), runner_method("raplace")], tmp_path / "out", cfg)
    for m, row in res["sequences"]["far"].items():
        assert row["n_revisit"] == 0 and row["f1max"] is None and row["recall@1"] is None, m
    assert "None%" not in caplog.text and "far ringkey: no revisit queries" in caplog.text
    md = results_markdown(res)
    # Recall@1 / F1max / SR / ê_r / ê_t: none applies (Recall@1 over all queries, 0 of 4, is in the second table)
    assert "| ringkey | – | – | – | – | – |" in md and "| raplace | – | – | – | – | – |" in md
    assert len(make_all_plots(res, tmp_path / "out")) == 2  # the PR legend reads 'F1max –'


# ---------------------------------------------------------------- findings 11, 12: help and wording
def test_limit_help_says_evenly_spread_and_that_query_limit_replaces_it():
    """QA 11: `--every 2 --limit 45` kept a linspace subset (5 m / 10 m keyframe gaps); the help did not say."""
    text = inspect.signature(bench).parameters["limit"].default.help
    assert "evenly spread" in text and "not the first N" in text
    assert "--query-limit, when given, replaces it for the query sequences" in text


def test_a_folder_run_names_its_database_folder_and_a_folder_among_the_scans_is_named(loop_sequences, tmp_path,
                                                                                      cache_env):
    """QA 12: results.md said 'suite `boreas-db`' for a folder run; a directory named 2500000.png among the scans
    was reported as 'no such scan file' after the features of the other scans were computed."""
    _, db, q = loop_sequences
    out = tmp_path / "out"
    r = _bench(["--database", str(db.root), "--query", str(q.root), "--preset", "boreas", "--methods", "ringkey",
                "--limit", "3", *FAST, "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert (out / "results.md").read_text().splitlines()[0] == "# `reradar bench` results — database folder `db-run`"
    assert results_markdown({"suite": "loop-sim", "settings": {}}).splitlines()[0] == (
        "# `reradar bench` results — suite `loop-sim`")

    bad = tmp_path / "with-dir"
    shutil.copytree(q.root, bad)
    odd = bad / "radar" / f"{int(q.timestamps_us[-1]) + 250_000}.png"
    odd.mkdir()
    with pytest.raises(DatasetError, match=rf"{odd.name}: is a folder, not a scan file"):
        pairs_from_folders(db.root, [bad], preset="boreas")
    r = _bench(["--database", str(db.root), "--query", str(bad), "--preset", "boreas", "--methods", "ringkey",
                *FAST, "--out", str(tmp_path / "out2")])
    assert r.exit_code == 2 and "is a folder, not a scan file" in r.output
