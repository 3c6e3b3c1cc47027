"""`reradar info`: a Navtech-layout .npy (the PNG's pixels saved with np.save) is read with --scan-layout navtech,
as its error message says (QA session 24, finding 5: `info` had no such option)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from typer.testing import CliRunner

from reradar_cli import app
from reradar_core.io.scan import RadarScan, encode_navtech_png_bytes


def _scan() -> RadarScan:
    rng = np.random.default_rng(0)
    power = (rng.random((400, 3768)) < 0.01).astype(np.float32)
    return RadarScan.from_power(power, "oxford", start_time_us=1_547_131_046_353_776)


def test_info_reads_a_navtech_npy_with_scan_layout_navtech(tmp_path: Path) -> None:
    png = tmp_path / "scan.png"
    png.write_bytes(encode_navtech_png_bytes(_scan()))
    npy = tmp_path / "nav.npy"
    np.save(npy, cv2.imdecode(np.frombuffer(png.read_bytes(), np.uint8), cv2.IMREAD_UNCHANGED))
    as_polar = CliRunner().invoke(app, ["info", str(npy)])
    assert as_polar.exit_code == 2 and "--scan-layout navtech on the command line" in as_polar.output
    res = CliRunner().invoke(app, ["info", "--scan-layout", "navtech", str(npy)])
    assert res.exit_code == 0, res.output
    from_png = CliRunner().invoke(app, ["info", str(png)])
    assert res.output.replace(str(npy), "F") == from_png.output.replace(str(png), "F")  # the same scan
    assert "timestamp: 1547131046353776 us" in res.output and "range bins: 3768" in res.output
    bad = CliRunner().invoke(app, ["info", "--scan-layout", "image", str(npy)])
    assert bad.exit_code == 2 and "must be polar or navtech" in bad.output
    polar = tmp_path / "polar.npy"
    np.save(polar, np.zeros((400, 3768), np.uint8))
    wrong = CliRunner().invoke(app, ["info", "--scan-layout", "navtech", str(polar)])
    assert wrong.exit_code == 2 and "polar.npy" in wrong.output and "Traceback" not in wrong.output
