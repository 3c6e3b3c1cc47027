"""``reradar sim`` into an existing folder: resumed only for the same parameters, refused or replaced (--overwrite)
otherwise, never removing files the simulator did not write; bad numbers are usage errors, not tracebacks."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from reradar_cli import app
from reradar_core.io.poses import PoseSequence, write_txyyaw_csv
from reradar_core.sim.writer import COMPLETE_MARKER


@pytest.fixture(scope="module")
def traj(tmp_path_factory) -> Path:
    """40 poses 0.25 s apart, 2 m steps along +x (the QA report's ``traj.csv``)."""
    t = np.arange(40, dtype=np.int64) * 250_000
    path = tmp_path_factory.mktemp("traj") / "traj.csv"
    write_txyyaw_csv(PoseSequence(t, np.column_stack([2.0 * np.arange(40), np.zeros(40)]), np.zeros(40)), path)
    return path


def _sim(traj: Path, out: Path, *args: str):
    return CliRunner().invoke(app, ["sim", "--trajectory", str(traj), "--out", str(out),
                                    *args])


def _digests(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.md5(p.read_bytes()).hexdigest() for p in sorted((folder / "radar").glob("*.png"))}


def test_other_parameters_are_refused_then_replaced_with_overwrite(traj, tmp_path):
    out = tmp_path / "seq"
    res = _sim(traj, out, "--limit", "4", "--condition", "snow_cover")
    assert res.exit_code == 0, res.output
    before = _digests(out)
    assert len(before) == 4
    # another condition / selection into the same folder: refused, nothing touched
    res = _sim(traj, out, "--limit", "3", "--every", "4", "--condition", "rain")
    assert res.exit_code == 2 and "--overwrite" in res.output and "condition snow_cover -> rain" in res.output
    assert "Traceback" not in res.output and _digests(out) == before
    # the lateral offset alone is another render too
    res = _sim(traj, out, "--limit", "4", "--condition", "snow_cover", "--lateral", "1.0")
    assert res.exit_code == 2 and "--overwrite" in res.output
    # --overwrite: the old scans are gone, only the new selection is there, with its metadata
    res = _sim(traj, out, "--limit", "3", "--every", "4", "--condition", "rain", "--overwrite")
    assert res.exit_code == 0, res.output
    after = _digests(out)
    assert sorted(after, key=lambda n: int(n[:-4])) == ["0.png", "1000000.png", "2000000.png"]
    assert after["0.png"] != before["0.png"]  # re-rendered in the rain, not kept from the snow render
    meta = json.loads((out / "reradar_sim.json").read_text())
    assert meta["condition"] == "rain" and meta["num_scans"] == 3


def test_same_parameters_resume_and_keep_only_the_selection(traj, tmp_path):
    out = tmp_path / "seq"
    assert _sim(traj, out, "--limit", "3").exit_code == 0
    ref = _digests(out)
    # an interrupted render: marker missing, one scan missing, a scan of no selection left behind
    (out / COMPLETE_MARKER).unlink()
    (out / "radar" / "500000.png").unlink()
    (out / "radar" / "9750000.png").write_bytes((out / "radar" / "0.png").read_bytes())
    kept = (out / "radar" / "0.png").stat().st_mtime_ns
    res = _sim(traj, out, "--limit", "3")
    assert res.exit_code == 0, res.output
    assert _digests(out) == ref  # the missing scan is back byte-identical, the stray one removed
    assert (out / "radar" / "0.png").stat().st_mtime_ns == kept  # resumed: the others were not re-rendered
    assert (out / COMPLETE_MARKER).is_file()


def test_folders_that_are_not_renders_are_never_cleared(traj, tmp_path):
    real = tmp_path / "real"
    (real / "radar").mkdir(parents=True)
    (real / "radar" / "1600000000000000.png").write_bytes(b"a real scan")
    for extra in ((), ("--overwrite",)):
        res = _sim(traj, real, "--limit", "2", *extra)
        assert res.exit_code == 2 and "not a simulator render" in res.output, res.output
    assert (real / "radar" / "1600000000000000.png").read_bytes() == b"a real scan"
    # a render with a file of the user's in it: refused, even with --overwrite
    out = tmp_path / "seq"
    assert _sim(traj, out, "--limit", "2").exit_code == 0
    (out / "notes.txt").write_text("mine")
    res = _sim(traj, out, "--limit", "2", "--condition", "rain", "--overwrite")
    assert res.exit_code == 2 and "notes.txt" in res.output
    assert (out / "notes.txt").read_text() == "mine"
    # --out naming a file
    res = _sim(traj, traj, "--limit", "2")
    assert res.exit_code == 2 and "is a file" in res.output and "Traceback" not in res.output


@pytest.mark.parametrize("args, what", [(["--every", "0"], "--every"), (["--every", "-1"], "--every"),
                                        (["--limit", "-38"], "--limit"), (["--lateral", "nan"], "--lateral")])
def test_bad_numbers_are_usage_errors(traj, tmp_path, args, what):
    res = _sim(traj, tmp_path / "seq", *args)
    assert res.exit_code == 2 and what in res.output and "Traceback" not in res.output
    assert not (tmp_path / "seq").exists()


def test_binary_trajectory_is_a_clean_error(tmp_path):
    binary = tmp_path / "grey.png"
    binary.write_bytes(bytes(range(256)) * 8)
    res = CliRunner().invoke(app, ["sim", "--trajectory", str(binary), "--time-unit", "s", "--out",
                                   str(tmp_path / "x")])
    assert res.exit_code == 2 and "not a text pose file" in res.output


@pytest.mark.parametrize("args", [["sim-suite", "smoke", "--every", "0"], ["sim-suite", "smoke", "--limit", "-1"],
                                  ["sim-report", "--real", ".", "--sim", ".", "--limit", "0"],
                                  ["sim-report", "--real", ".", "--sim", ".", "--limit", "-1"]])
def test_suite_and_report_counts_must_be_positive(args, tmp_path):
    res = CliRunner().invoke(app, [*args[:2], *(["--root", str(tmp_path)] if args[0] == "sim-suite" else []),
                                   *args[2:]])
    assert res.exit_code == 2 and "greater than or equal to 1" in res.output
    assert not any(tmp_path.iterdir())


def test_help_names_the_profiles_resume_and_suite_folder():
    from reradar_core.sim.world import PROFILES

    text = CliRunner().invoke(app, ["sim", "--help"], terminal_width=200).output
    assert all(name in text for name in PROFILES) and "--overwrite" in text and "resumed" in text
    text = CliRunner().invoke(app, ["sim-suite", "--help"], terminal_width=200).output
    assert "sim/v<simulator version>/<name>" in text


def test_tile_types_renders_a_periodic_world_recorded_as_another_render(traj, tmp_path):
    """``--tile-types 1`` (every 40 m tile one layout, as the confidence fit's periodic worlds) is another world:
    other scans, recorded in the folder's metadata, and refused into a render of the plain world."""
    plain, periodic = tmp_path / "plain", tmp_path / "periodic"
    assert _sim(traj, plain, "--limit", "2", "--seed", "3").exit_code == 0
    res = _sim(traj, periodic, "--limit", "2", "--seed", "3", "--tile-types", "1")
    assert res.exit_code == 0, res.output
    assert _digests(periodic) != _digests(plain)
    assert json.loads((periodic / "reradar_sim.json").read_text())["tile_types"] == 1
    res = _sim(traj, plain, "--limit", "2", "--seed", "3", "--tile-types", "1")
    assert res.exit_code == 2 and "--overwrite" in res.output
    assert _sim(traj, tmp_path / "bad", "--tile-types", "-1").exit_code == 2
