"""Scan statistics and the real-vs-simulated report (known-answer arrays; folders made by the tests)."""

from __future__ import annotations

import numpy as np
from typer.testing import CliRunner

from reradar_core.io.datasets import write_sequence_scan
from reradar_core.io.scan import RadarScan
from reradar_core.sim.report import compare_table, folder_statistics
from reradar_core.sim.stats import RANGE_BANDS_M, scan_statistics


def _scan(power: np.ndarray, t0: int = 1_600_000_000_000_000) -> RadarScan:
    return RadarScan.from_power(power.astype(np.float32), "oxford", start_time_us=t0)


def test_scan_statistics_known_answers():
    power = np.zeros((400, 3768), np.float32)
    power[:, ::2] = 0.5  # half the bins at 0.5, half at 0
    st = scan_statistics(_scan(power), with_keypoints=False)
    assert st.mean == 0.25 and st.frac_zero == 0.5 and st.p50 == 0.25
    assert st.p99 == 0.5
    assert len(st.band_mean) == len(RANGE_BANDS_M)
    np.testing.assert_allclose(st.band_mean, 0.25, atol=0.01)
    assert abs(sum(st.hist) - 1.0) < 1e-9 and st.hist[0] == 0.5 and st.hist[8] == 0.5
    # the far quarter sets the floor: nothing lies above it here
    assert st.frac_above_floor == 0.0


def test_scan_statistics_counts_a_bright_target():
    rng = np.random.default_rng(0)
    power = (rng.random((400, 3768)) * 0.05).astype(np.float32)
    power[100:103, 1000:1010] = 0.9  # one strong reflector at ~43 m
    st = scan_statistics(_scan(power))
    assert st.keypoints >= 1
    assert st.frac_above_floor > 0
    assert st.band_mean[4] > st.band_mean[5]  # 25-50 m band holds the target


def test_sim_report_cli_on_generated_folders(tmp_path):
    from reradar_cli import app

    rng = np.random.default_rng(1)
    for name, level in (("a", 0.05), ("b", 0.1)):
        folder = tmp_path / name
        for k in range(2):
            power = (rng.random((400, 3768)) * level).astype(np.float32)
            write_sequence_scan(folder, "oxford", _scan(power, 1_600_000_000_000_000 + k * 250_000))
    # a folder of PNGs without poses is accepted as the "real" side
    res = CliRunner().invoke(app, ["sim-report", "--real", str(tmp_path / "a" / "radar"), "--sim",
                                   str(tmp_path / "b" / "radar"), "--limit", "2",
                                   "--images", str(tmp_path / "img" / "prev")])
    assert res.exit_code == 0, res.output
    assert "| mean power |" in res.output and "| statistic | real | radar |" in res.output
    assert (tmp_path / "img" / "prev_real_cart.png").is_file()
    stats = folder_statistics(tmp_path / "b" / "radar", limit=2)
    assert stats["num_scans"] == 2 and 0.04 < stats["mean"] < 0.06
    table = compare_table({"x": stats})
    assert table.splitlines()[0] == "| statistic | x |"
    missing = CliRunner().invoke(app, ["sim-report", "--real", str(tmp_path / "nothing"), "--sim", str(tmp_path)])
    assert missing.exit_code == 2


def test_sim_report_keeps_folders_that_share_a_name_and_writes_into_an_images_folder(tmp_path):
    """QA (session 20): ``--sim a/seq --sim b/seq`` reported one column (the second overwrote the first) and
    ``--images dir/`` wrote ``dir_*.png`` beside the folder."""
    from reradar_cli import app

    rng = np.random.default_rng(2)
    for name, level in (("real", 0.05), ("a", 0.05), ("b", 0.2)):
        folder = tmp_path / name / "seq"
        for k in range(2):
            power = (rng.random((400, 3768)) * level).astype(np.float32)
            write_sequence_scan(folder, "oxford", _scan(power, 1_600_000_000_000_000 + k * 250_000))
    (tmp_path / "img").mkdir()
    res = CliRunner().invoke(app, ["sim-report", "--real", str(tmp_path / "real" / "seq"), "--sim",
                                   str(tmp_path / "a" / "seq"), "--sim", str(tmp_path / "b" / "seq"), "--limit", "2",
                                   "--images", str(tmp_path / "img")])
    assert res.exit_code == 0, res.output
    assert "| statistic | real | a/seq | b/seq |" in res.output
    written = sorted(p.name for p in (tmp_path / "img").iterdir())
    assert written == sorted(f"preview_{n}_{kind}.png" for n in ("real", "a_seq", "b_seq") for kind in ("cart", "polar"))
    twice = CliRunner().invoke(app, ["sim-report", "--real", str(tmp_path / "real" / "seq"), "--sim",
                                     str(tmp_path / "a" / "seq"), "--sim", str(tmp_path / "a" / "seq")])
    assert twice.exit_code == 2 and "same folder twice" in twice.output


def test_sim_report_names_each_folders_preset(tmp_path):
    """QA session 36: Oxford scans beside Boreas-preset renders were compared without a word: each column names the
    preset its scans were read with (the command adds a note when they differ)."""
    from reradar_cli import app

    rng = np.random.default_rng(3)
    for name in ("ox", "ox2"):
        for k in range(2):
            power = (rng.random((400, 3768)) * 0.05).astype(np.float32)
            write_sequence_scan(tmp_path / name, "oxford", _scan(power, 1_600_000_000_000_000 + k * 250_000))
    assert folder_statistics(tmp_path / "ox" / "radar", limit=2)["radar_preset"] == "oxford"
    res = CliRunner().invoke(app, ["sim-report", "--real", str(tmp_path / "ox" / "radar"), "--sim",
                                   str(tmp_path / "ox2" / "radar"), "--limit", "2"])
    assert res.exit_code == 0, res.output
    assert "| radar preset | oxford | oxford |" in res.output and "note:" not in res.output
    table = compare_table({"a": {**folder_statistics(tmp_path / "ox" / "radar", limit=2), "radar_preset": "boreas"}})
    assert "| radar preset | boreas |" in table
