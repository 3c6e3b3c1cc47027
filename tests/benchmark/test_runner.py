"""End-to-end harness runs on two tiny synthetic sequences (harness behaviour, not accuracy claims)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from reradar_core.baselines import BASELINES, make_method
from reradar_core.benchmark.plots import make_all_plots
from reradar_core.benchmark.results import results_markdown, write_results
from reradar_core.benchmark.runner import BenchConfig, BenchPair, run_benchmark

KEYS = {"recall@1", "f1max", "sr", "e_r_deg", "e_t_m", "n_queries", "ms_per_query"}


def test_run_benchmark_all_baselines_results_plots_and_cache(loop_sequences, tmp_path):
    _, db, q = loop_sequences
    methods = [make_method(n) for n in BASELINES]
    cfg = BenchConfig(radius_m=20.0, cache_root=tmp_path / "features", progress=False)
    res = run_benchmark([BenchPair("query-run", db, q)], methods, tmp_path / "out", cfg, suite="synthetic")
    rows = res["sequences"]["query-run"]
    assert set(rows) == set(BASELINES)
    for name, r in rows.items():
        assert KEYS <= set(r), name
        assert r["n_queries"] == len(q) == 12
        assert 0.0 <= r["recall@1"] <= 100.0
    # the queries drive the database's loop 2 m to the side: an easy case for the Radon descriptor
    assert rows["raplace"]["recall@1"] >= 90.0
    # SR applicability follows the paper's rules
    assert rows["ringkey"]["sr"] is None and rows["radvlad"]["sr"] is None
    assert rows["referee"]["sr"] is not None and rows["referee"]["e_t_m"] is None
    stress = res["rotation_stress"]["query-run"]
    assert set(stress) == set(BASELINES)
    assert stress["radvlad"]["recall@1_rotated"] >= 85.0  # rotation-invariant by design (orderless beams)
    assert stress["ringkey"]["drop"] == pytest.approx(
        stress["ringkey"]["recall@1"] - stress["ringkey"]["recall@1_rotated"])

    jpath, mpath = write_results(res, tmp_path / "out")
    loaded = json.loads(jpath.read_text())
    assert loaded["suite"] == "synthetic" and "query-run" in loaded["sequences"]
    md = mpath.read_text()
    assert "| Method | query-run: Recall@1 (%)" in md and "| raplace |" in md and "Rotation stress" in md
    figs = make_all_plots(res, tmp_path / "out")
    assert {p.name for p in figs} >= {"pr_query-run.png", "trajectory_query-run.png", "rotation_stress.png"}
    assert all(p.stat().st_size > 1000 for p in figs)

    # second run: every prepared record comes from the cache, results identical
    for m in methods:
        m.prepare = _fail  # type: ignore[method-assign]
    res2 = run_benchmark([BenchPair("query-run", db, q)], methods, tmp_path / "out2", cfg, suite="synthetic")
    for name in BASELINES:
        assert res2["sequences"]["query-run"][name]["recall@1"] == rows[name]["recall@1"]


def _fail(scan):
    raise AssertionError("prepare() called although the feature cache holds the scan")


def test_markdown_marks_best_and_not_applicable():
    res = {"suite": "s", "settings": {"radius_m": 20.0, "pairs": {}},
           "sequences": {"q": {"a": {"recall@1": 90.0, "f1max": 91.0, "sr": None, "e_r_deg": None, "e_t_m": None,
                                      "ms_per_query": 1.0},
                                "b": {"recall@1": 95.0, "f1max": 80.0, "sr": 93.0, "e_r_deg": 0.5, "e_t_m": 1.2,
                                      "ms_per_query": 2.0}}}}
    md = results_markdown(res)
    assert "Descriptor network" not in md  # no learned method: nothing to say
    assert "| a | 90.00 | **91.00** | – | – | – |" in md
    assert "| b | **95.00** | 80.00 | **93.00** | **0.50** | **1.20** |" in md
    assert "| b | 2.0 |" in md
    res["settings"]["network_runtime"] = {"b": "onnx"}
    assert "Descriptor network: b in onnx (`RERADAR_NETWORK_RUNTIME`" in results_markdown(res)
    assert "Global descriptor alone:" not in md  # no row reads a descriptor alone: nothing to explain
    res["sequences"]["q"]["b"]["recall@1_descriptor"] = 88.0
    assert "Global descriptor alone: the place of the nearest map descriptor" in results_markdown(res)


def test_cli_bench_on_real_layout_folders(loop_sequences, tmp_path, cache_env):
    from reradar_cli import app

    root, _, _ = loop_sequences
    out = tmp_path / "bench-out"
    r = CliRunner().invoke(app, ["bench", "--database", str(root / "db-run"), "--query", str(root / "query-run"),
                                 "--preset", "boreas", "--methods", "ringkey,raplace", "--every", "2",
                                 "--no-timing", "--no-yaw-curve", "--no-rotation", "--out", str(out)])
    assert r.exit_code == 0, r.output
    res = json.loads((out / "results.json").read_text())
    assert res["settings"]["radius_m"] == 20.0  # Boreas radius from the preset
    row = res["sequences"]["query-run"]["raplace"]
    assert KEYS <= set(row) and row["n_queries"] == 6
    assert (out / "results.md").is_file() and (out / "pr_query-run.png").is_file()
    assert np.isfinite(row["ms_per_query"])


def test_cli_rejects_ambiguous_input(tmp_path):
    from reradar_cli import app

    r = CliRunner().invoke(app, ["bench", "--out", str(tmp_path)])
    assert r.exit_code != 0
    assert "--suite" in r.output


def test_descriptor_recall_at_1_known_answer():
    """Descriptor-only Recall@1 counts the global top 1 against the revisit queries only."""
    from reradar_core.benchmark.runner import descriptor_recall_at_1

    db = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [200.0, 0.0, 0.0]])
    q = np.array([[1.0, 0.0, 0.0], [101.0, 0.0, 0.0], [199.0, 0.0, 0.0], [500.0, 0.0, 0.0]])
    positive = np.array([True, True, True, False])  # the last query has no keyframe within 20 m
    # right, wrong, right; the no-match query's answer does not count
    by_descriptor = np.array([0, 2, 2, 1])
    assert descriptor_recall_at_1(by_descriptor, positive, q, db, 20.0) == pytest.approx(200.0 / 3)
    # a method that does not re-rank reports none (its headline Recall@1 is the descriptor's)
    assert descriptor_recall_at_1(np.full(4, -1), positive, q, db, 20.0) is None


def test_per_database_work_runs_once_before_the_timed_queries():
    """``ready_database`` (a method's one-off work per database, e.g. ReRadar's preloaded screen data) runs once,
    after ``build_index`` and before the first query, so per-query times never include it."""
    from reradar_core.baselines.base import PlaceRecognitionMethod
    from reradar_core.benchmark.runner import PreparedSet, evaluate_method

    events: list[str] = []

    class Toy(PlaceRecognitionMethod):
        name = "toy"

        def prepare(self, scan):  # noqa: ANN001, ANN202 - records are built directly below
            raise AssertionError("not called: the records are prepared already")

        def describe_prepared(self, prepared):  # noqa: ANN001, ANN202
            return np.asarray(prepared["x"], np.float64)

        def build_index(self, db_descs):  # noqa: ANN001, ANN202
            events.append("index")
            return super().build_index(db_descs)

        def ready_database(self, index, db_prepared, db_poses):  # noqa: ANN001, ANN202
            events.append("ready")

        def distance(self, q_desc, index):  # noqa: ANN001, ANN202
            events.append("query")
            return np.abs(index[:, 0] - q_desc[0])

    db_poses = np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [100.0, 0.0, 0.0]])
    q_poses = np.array([[1.0, 0.0, 0.0], [99.0, 0.0, 0.0]])
    db = PreparedSet([{"x": [p[0]]} for p in db_poses], np.zeros(3))
    q = PreparedSet([{"x": [p[0]]} for p in q_poses], np.zeros(2))
    run = evaluate_method(Toy(), db, db_poses, q, q_poses, 20.0)
    assert events == ["index", "ready", "query", "query"]
    assert run.summary["recall@1"] == pytest.approx(100.0)
