"""``reradar localize --follow``: Ctrl-C (KeyboardInterrupt) during a replay stops sending, prints the summary of
the scans answered so far under an "interrupted after N of M scans" line, writes the trajectory and exits 130 (a
Ctrl-C used to end in click's "Aborted!" with exit 1, the summary and the plot lost).

The server is faked with ``httpx.MockTransport`` (no network): scan k of the drive is answered ``localized`` at
its ground-truth pose (even k) or ``not_localized`` (odd k), and the request for scan ``stop_at`` raises
KeyboardInterrupt, as a Ctrl-C while the client waits for that answer does. The summary's counts follow by hand.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from pathlib import Path

import httpx
import pytest
import typer
from typer.testing import CliRunner

import service.follow as follow
from reradar_core.io.datasets import write_sequence_poses, write_sequence_scan
from reradar_core.io.poses import PoseSequence
from service import client as client_module
from service.cli import register
from service.follow import INTERRUPTED_EXIT, interrupted_line

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import keyframe_poses, keyframe_time, make_scan  # noqa: E402

Handler = Callable[[httpx.Request], httpx.Response]

N_SCANS = 5
POSES = keyframe_poses()[:N_SCANS]  # (x m, y m, yaw rad): 40 m apart; the drive's ground truth at mid-sweep


def _answer(k: int) -> dict:
    """The fake server's answer to the drive's k-th scan: localized at its ground truth (even k) or not (odd)."""
    base = {"map_id": "m", "scan_id": None, "timings_ms": {"total_ms": 5.0}}
    if k % 2:
        return {**base, "status": "not_localized", "reason": "no_candidate"}
    x, y, yaw = POSES[k]
    return {**base, "status": "localized", "pose": {"x_m": float(x), "y_m": float(y),
                                                    "yaw_deg": math.degrees(float(yaw))},
            "alignment_score": 0.9, "confidence": 0.99}


def _drive(root: Path, n: int = N_SCANS) -> Path:
    """A Boreas-layout folder of ``n`` scans 0.25 s apart, with poses at their mid-sweep times."""
    seq = root / "drive"
    times = [keyframe_time(0) + 10_000_000 + i * 250_000 for i in range(n)]
    for i, t in enumerate(times):
        write_sequence_scan(seq, "boreas", make_scan(i, t))
    write_sequence_poses(seq, "boreas", PoseSequence([t + 124_688 for t in times], POSES[:n, :2], POSES[:n, 2]))
    return seq


def _fake_server(monkeypatch: pytest.MonkeyPatch, stop_at: int | None) -> list[httpx.Request]:
    """Every request the CLI's client sends, recorded; the k-th answered by ``_answer(k)``, the ``stop_at``-th
    interrupted (KeyboardInterrupt raised from the transport, as a Ctrl-C during the wait for it)."""
    seen: list[httpx.Request] = []

    def handle(request: httpx.Request) -> httpx.Response:
        k = len(seen)
        seen.append(request)
        if k == stop_at:
            raise KeyboardInterrupt
        return httpx.Response(200, json=_answer(k))

    init = client_module.ReRadarClient.__init__
    monkeypatch.setattr(client_module.ReRadarClient, "__init__",
                        lambda self, base_url, **kw: init(self, base_url, transport=httpx.MockTransport(handle)))
    return seen


def _replay(seq: Path, png: Path) -> object:
    app = typer.Typer()
    register(app)
    return CliRunner().invoke(app, ["localize", "--follow", str(seq), "--server", "http://x", "--map", "m",
                                    "--preset", "boreas", "--out", str(png), "--odometry-noise", "0"])


def _rows(output: str) -> list[str]:
    return [ln for ln in output.splitlines() if ln[:4].strip().isdigit()]


def test_interrupted_line_says_how_many_scans_were_answered() -> None:
    assert interrupted_line(2, 5) == ("interrupted after 2 of 5 scans (Ctrl-C): the summary below covers the 2 "
                                      "answered")
    assert INTERRUPTED_EXIT == 130


# stop_at scans answered: localized at even k (0, 2, 4), not localized at odd k
@pytest.mark.parametrize(("stop_at", "localized"), [(1, 1), (2, 1), (3, 2), (4, 2)])
def test_ctrl_c_prints_the_partial_summary_writes_the_plot_and_exits_130(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path, stop_at: int, localized: int) -> None:
    pytest.importorskip("matplotlib")
    seen = _fake_server(monkeypatch, stop_at)
    png = tmp_path / "t.png"
    res = _replay(_drive(tmp_path), png)
    assert res.exit_code == 130, res.output
    assert len(seen) == stop_at + 1  # nothing sent after the interrupted request
    assert len(_rows(res.output)) == stop_at
    n, missed = stop_at, stop_at - localized
    assert f"interrupted after {n} of {N_SCANS} scans (Ctrl-C)" in res.output
    assert (f"success (< 20 m and < 10 deg): {localized}/{n} ({100 * localized / n:.1f} %); localized at a wrong "
            f"pose: 0/{n}; not localized: {missed}/{n}") in res.output
    assert f"pose accuracy (<= 2 m and <= 2 deg): {localized}/{n} ({100 * localized / n:.1f} %)" in res.output
    assert f"trajectory: {png}" in res.output and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "Aborted" not in res.output
    # the summary comes after the interrupted line
    assert res.output.index("interrupted after") < res.output.index("success (")


def test_ctrl_c_before_any_answer_exits_130_with_no_scans_and_no_plot(monkeypatch: pytest.MonkeyPatch,
                                                                      tmp_path: Path) -> None:
    seen = _fake_server(monkeypatch, stop_at=0)
    png = tmp_path / "t.png"
    res = _replay(_drive(tmp_path), png)
    assert res.exit_code == 130, res.output
    assert len(seen) == 1 and _rows(res.output) == []
    assert f"interrupted after 0 of {N_SCANS} scans" in res.output and "no scans" in res.output
    assert not png.exists()


def test_exit_codes_without_ctrl_c_are_unchanged(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """The same fake drive replayed to its end: 2 of 5 not localized is no failure of the replay itself, but
    every localized answer is at its ground truth: exit 0 (and 1 once nothing localized)."""
    pytest.importorskip("matplotlib")
    _fake_server(monkeypatch, stop_at=None)
    res = _replay(_drive(tmp_path), tmp_path / "t.png")
    assert res.exit_code == 0, res.output
    assert "interrupted" not in res.output
    assert f"success (< 20 m and < 10 deg): 3/{N_SCANS} (60.0 %)" in res.output


def test_ctrl_c_during_a_busy_wait_stops_the_retries(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Ctrl-C while the replay waits to retry a busy server (503): no further try, the partial summary, 130."""
    pytest.importorskip("matplotlib")
    seen: list[httpx.Request] = []

    def handle(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        if len(seen) == 1:
            return httpx.Response(200, json=_answer(0))
        return httpx.Response(503, json={"error": "overloaded", "detail": "retry in 1 s"},
                              headers={"content-type": "application/problem+json"})

    def sleep(seconds: float) -> None:
        raise KeyboardInterrupt

    init = client_module.ReRadarClient.__init__
    monkeypatch.setattr(client_module.ReRadarClient, "__init__",
                        lambda self, base_url, **kw: init(self, base_url, transport=httpx.MockTransport(handle)))
    monkeypatch.setattr(follow.time, "sleep", sleep)
    res = _replay(_drive(tmp_path), tmp_path / "t.png")
    assert res.exit_code == 130, res.output
    assert len(seen) == 2  # scan 0 answered, scan 1 refused busy once: no retry after the Ctrl-C
    assert f"interrupted after 1 of {N_SCANS} scans" in res.output
    assert "success (< 20 m and < 10 deg): 1/1 (100.0 %)" in res.output


def test_a_second_ctrl_c_during_the_summary_exits_130_at_once(monkeypatch: pytest.MonkeyPatch,
                                                               tmp_path: Path) -> None:
    """A second Ctrl-C while the trajectory is drawn ends the command there: 130, no traceback, no 'Aborted!'."""

    def plot(*args: object) -> None:
        raise KeyboardInterrupt

    _fake_server(monkeypatch, stop_at=2)
    monkeypatch.setattr(follow, "_plot", plot)
    png = tmp_path / "t.png"
    res = _replay(_drive(tmp_path), png)
    assert res.exit_code == 130, res.output
    assert "interrupted after 2 of 5 scans" in res.output and "success (< 20 m and < 10 deg): 1/2" in res.output
    assert "trajectory:" not in res.output and not png.exists()
    assert "interrupted (Ctrl-C)" in res.output and "Aborted" not in res.output
    assert not isinstance(res.exception, KeyboardInterrupt)


def test_ctrl_c_during_a_single_scan_exits_130_not_1(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Exit 1 means "not localized": a Ctrl-C while one scan is localized is 130 too."""
    from reradar_core.io.scan import write_navtech_png

    _fake_server(monkeypatch, stop_at=0)
    scan = write_navtech_png(make_scan(0, keyframe_time(0)), tmp_path / "q.png")
    app = typer.Typer()
    register(app)
    res = CliRunner().invoke(app, ["localize", str(scan), "--server", "http://x", "--map", "m",
                                   "--preset", "boreas"])
    assert res.exit_code == 130, res.output
    assert "interrupted (Ctrl-C)" in res.output and "Aborted" not in res.output
