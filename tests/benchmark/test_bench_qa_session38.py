"""QA session 38 on `reradar bench`: heading-only methods scored at mid-sweep, the feature cache keyed by the radar
preset, a copied database refused, thinned runs said so, stale figures removed, one run per --out, methods checked
before a suite renders."""

from __future__ import annotations

import fcntl
import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from reradar_core.baselines.base import PlaceRecognitionMethod, Retrieval
from reradar_core.benchmark.cache import sequence_key
from reradar_core.benchmark.runner import PreparedSet, evaluate_method

FAST = ["--no-timing", "--no-yaw-curve", "--no-rotation", "--no-plots"]


def _bench(args: list[str]):
    from reradar_cli import app

    return CliRunner().invoke(app, ["bench", *args])


class _HeadingOracle(PlaceRecognitionMethod):
    """Retrieves query i's keyframe i and answers the heading between the two sweeps' mid-sweep poses exactly."""

    name = "heading-oracle"
    provides_heading = True

    def __init__(self, mid_db: np.ndarray, mid_q: np.ndarray) -> None:
        self.mid_db, self.mid_q = mid_db, mid_q

    def prepare(self, scan):  # pragma: no cover - records are given
        raise AssertionError

    def describe_prepared(self, prepared):
        return np.asarray([prepared["i"]], float)

    def distance(self, q_desc, index):
        return np.abs(index[:, 0] - q_desc[0])

    def localize(self, q_prepared, q_desc, index, db_prepared, db_poses):
        i = int(q_prepared["i"])
        return Retrieval(i, 0.0, float(self.mid_q[i, 2] - self.mid_db[i, 2]))


def test_a_heading_only_method_is_scored_against_mid_sweep_poses() -> None:
    """At a corner the scan-timestamp yaw lies 15-25 degrees from the mid-sweep one: ReFeree's right headings were
    counted as failures."""
    n = 5
    stamp = np.c_[np.arange(n) * 10.0, np.zeros(n), np.zeros(n)]
    mid_db = stamp + [0.0, 0.0, 0.3]  # the sweep turned 0.3 rad by its middle
    mid_q = stamp + [1.0, 0.0, 0.5]
    recs = [{"i": i} for i in range(n)]
    method = _HeadingOracle(mid_db, mid_q)
    run = evaluate_method(method, PreparedSet(recs, np.zeros(n)), stamp, PreparedSet(recs, np.zeros(n)),
                          stamp + [1.0, 0.0, 0.0], 20.0, pose_refs=(mid_db, mid_q))
    np.testing.assert_allclose(run.outcome.heading_err_deg, 0.0, atol=1e-9)
    assert run.summary["sr"] == pytest.approx(100.0)


def test_feature_cache_key_names_the_preset(tmp_path: Path) -> None:
    a, b = sequence_key("seq", tmp_path, "boreas"), sequence_key("seq", tmp_path, "boreas-2021")
    assert a != b and a == sequence_key("seq", tmp_path, "boreas") and a.startswith("seq-")


def test_a_copy_of_the_database_is_refused_as_a_query(loop_sequences, tmp_path, cache_env) -> None:
    import shutil

    _, db, _ = loop_sequences
    copy = tmp_path / "copy"
    shutil.copytree(db.root, copy)
    r = _bench(["--database", str(db.root), "--query", str(copy), "--preset", "boreas", "-m", "ringkey", *FAST,
                "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "a copy of it" in r.output


def test_thinned_runs_say_so_and_stale_figures_go(loop_sequences, tmp_path, cache_env) -> None:
    _, db, q = loop_sequences
    out = tmp_path / "o"
    out.mkdir()
    (out / "pr_old.png").write_bytes(b"png")
    (out / "results.json").write_text(json.dumps({"figures": ["pr_old.png"]}))
    (out / "notes.png").write_bytes(b"mine")  # not a figure of a run: stays
    r = _bench(["--database", str(db.root), "--query", str(q.root), "--preset", "boreas", "-m", "ringkey",
                "--limit", "6", "--query-limit", "4", *FAST, "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "at most 6 scans per sequence and at most 4 queries per query sequence" in r.output
    md = (out / "results.md").read_text()
    assert "at most 6 scans per sequence" in md
    assert not (out / "pr_old.png").exists() and (out / "notes.png").exists()


def test_one_run_per_out_folder(loop_sequences, tmp_path, cache_env) -> None:
    _, db, q = loop_sequences
    out = tmp_path / "o"
    out.mkdir()
    with (out / ".reradar-bench.lock").open("w") as held:  # another run holds the folder
        fcntl.flock(held.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        r = _bench(["--database", str(db.root), "--query", str(q.root), "--preset", "boreas", "-m", "ringkey",
                    *FAST, "--out", str(out)])
    assert r.exit_code == 2 and "another reradar bench run" in " ".join(r.output.replace("│", " ").split())
    assert not (out / "results.json").exists()


def test_an_unknown_method_is_refused_before_a_suite_renders(tmp_path, cache_env) -> None:
    r = _bench(["--suite", "smoke", "-m", "ringkey,nosuch", *FAST, "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "nosuch" in r.output
    assert not (cache_env / "sim").exists()  # nothing rendered
