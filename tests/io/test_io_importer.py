"""Importing foreign polar scans: range resampling, orientation, and the reader's refusal of raw ones."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from reradar_core.errors import ScanFormatError
from reradar_core.io.importer import ForeignScanLayout, import_polar_scan
from reradar_core.io.presets import get_preset
from reradar_core.io.scan import load_scan, write_navtech_png


def _foreign(n_az: int = 400, n_bins: int = 576, peak_bin: int = 57) -> np.ndarray:
    arr = np.zeros((n_az, n_bins), np.uint8)
    arr[:, peak_bin] = 255
    return arr


def test_peak_lands_at_same_range_on_preset_grid():
    # bin 57 at 0.175 m = 9.975 m; Boreas bins: range = -0.31 + i * 0.0596 -> i = 172.6
    scan = import_polar_scan(_foreign(), ForeignScanLayout(0.175), "boreas")
    p = get_preset("boreas")
    assert scan.power.shape == (p.num_azimuths, p.num_range_bins)
    peak = int(np.argmax(scan.power[0]))
    assert abs(scan.ranges_m[peak] - 57 * 0.175) < 0.175
    # beyond the source's last bin (575 * 0.175 = 100.6 m) there is no return
    assert np.all(scan.power[:, scan.ranges_m > 101.0] == 0)


def test_transposed_source_gives_same_scan():
    a = import_polar_scan(_foreign(), ForeignScanLayout(0.175), "oxford")
    b = import_polar_scan(_foreign().T.copy(), ForeignScanLayout(0.175, azimuth_axis=1), "oxford")
    np.testing.assert_array_equal(a.power, b.power)


def test_azimuth_count_resampled_circularly():
    arr = np.zeros((200, 100), np.uint8)
    arr[0] = 255  # only the first beam
    scan = import_polar_scan(arr, ForeignScanLayout(1.0), "oxford")
    row_energy = scan.power.sum(axis=1)
    assert scan.num_azimuths == 400
    # dst rows sit at src 0, 0.5, 1, ...: rows 1 and 399 (src 199.5, wrapping to src 0) hold half the beam
    assert row_energy[0] == 2 * row_energy[1] == 2 * row_energy[-1] > 0
    assert row_energy[2] == 0 and row_energy[-2] == 0


def test_imported_scan_round_trips_through_reader(tmp_path):
    scan = import_polar_scan(_foreign(), ForeignScanLayout(0.175), "boreas", start_time_us=1_600_000_000_000_000)
    back = load_scan(write_navtech_png(scan, tmp_path / "1600000000000000.png"), "boreas")
    assert back.num_range_bins == 3360 and back.timestamp_us >= 1_600_000_000_000_000


def test_reader_refuses_foreign_png_with_reason(tmp_path):
    rng = np.random.default_rng(0)
    raw = (rng.random((400, 576)) ** 4 * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "f.png"), raw)
    with pytest.raises(ScanFormatError, match="no Navtech metadata columns or is transposed"):
        load_scan(tmp_path / "f.png", "boreas")
    with pytest.raises(ScanFormatError, match="import-scans"):
        load_scan(tmp_path / "f.png")


def test_reader_refuses_more_bins_than_preset(tmp_path):
    scan = import_polar_scan(_foreign(n_bins=4000), ForeignScanLayout(0.0432), "oxford")
    path = write_navtech_png(scan, tmp_path / "s.png")
    with pytest.raises(ScanFormatError, match="3768 range bins, but preset 'boreas' has 3360"):
        load_scan(path, "boreas")


def test_bad_layout_values_refused():
    with pytest.raises(ScanFormatError):
        ForeignScanLayout(0.0)
    with pytest.raises(ScanFormatError, match="rescale"):
        import_polar_scan(np.full((10, 10), 2.0), ForeignScanLayout(0.1), "oxford")


def test_cli_imports_a_folder(tmp_path):
    import typer

    from reradar_core.cli_commands import import_scans

    app = typer.Typer()
    import_scans.register(app)

    @app.callback()
    def _root() -> None:  # a group, so the sub-command name is used as on the real CLI
        pass

    src = tmp_path / "src"
    src.mkdir()
    cv2.imwrite(str(src / "1600000000000000.png"), _foreign())
    res = CliRunner().invoke(app, ["import-scans", str(src / "1600000000000000.png"), "--out", str(tmp_path / "o"),
                                   "--range-resolution", "0.175", "--preset", "mulran"])
    assert res.exit_code == 0, res.output
    scan = load_scan(tmp_path / "o" / "1600000000000000.png", "mulran")
    assert scan.num_range_bins == 3360


def _import(tmp_path, *sources, out: str = "o"):
    from reradar_cli import app

    return CliRunner().invoke(app, ["import-scans", *map(str, sources), "--out", str(tmp_path / out),
                                    "--range-resolution", "0.175"])


def test_cli_refuses_sources_that_would_overwrite_each_other(tmp_path):
    """M4: two inputs named by the same timestamp once wrote one file and said 'wrote 2'."""
    for d in ("d1", "d2"):
        (tmp_path / d).mkdir()
        cv2.imwrite(str(tmp_path / d / "1566535872045000.png"), _foreign())
        cv2.imwrite(str(tmp_path / d / "1566535872295000.png"), _foreign())
    res = _import(tmp_path, *(tmp_path / d / n for d in ("d1", "d2")
                              for n in ("1566535872045000.png", "1566535872295000.png")))
    assert res.exit_code == 2 and "same timestamp" in res.output
    assert "d1/1566535872045000.png" in res.output and "d2/1566535872045000.png" in res.output
    assert not (tmp_path / "o").exists()


def test_cli_reads_nanosecond_names_and_refuses_other_numeric_names(tmp_path):
    cv2.imwrite(str(tmp_path / "1566535872045000123.png"), _foreign())  # MulRan: ns
    res = _import(tmp_path, tmp_path / "1566535872045000123.png")
    assert res.exit_code == 0, res.output
    assert [p.name for p in (tmp_path / "o").iterdir()] == ["1566535872045000.png"]
    assert load_scan(tmp_path / "o" / "1566535872045000.png", "boreas").timestamp_us == 1566535872045000
    cv2.imwrite(str(tmp_path / "1566535872045.png"), _foreign())  # ms? 13 digits: not guessed
    res = _import(tmp_path, tmp_path / "1566535872045.png", out="o2")
    assert res.exit_code == 2 and "13-digit" in res.output and "16 digits" in res.output


def test_cli_refuses_tiny_colour_and_navtech_sources(tmp_path):
    np.save(tmp_path / "small.npy", np.zeros((3, 3), np.uint8))
    res = _import(tmp_path, tmp_path / "small.npy")
    assert res.exit_code == 2 and "small.npy" in res.output and "3 azimuths x 3 range bins" in res.output
    cv2.imwrite(str(tmp_path / "rgb.png"), np.dstack([_foreign()] * 3))
    res = _import(tmp_path, tmp_path / "rgb.png")
    assert res.exit_code == 2 and "3-channel colour image" in res.output
    scan = import_polar_scan(_foreign(), ForeignScanLayout(0.175), "boreas", start_time_us=1_600_000_000_000_000)
    navtech = write_navtech_png(scan, tmp_path / "1600000000000000.png")
    res = _import(tmp_path, navtech)
    assert res.exit_code == 2 and "already a Navtech scan" in res.output and "needs no import" in res.output
    assert not (tmp_path / "o").exists()


def test_a_source_range_that_misses_the_preset_is_refused_and_angles_wrap():
    """QA (session 20): an offset of 500 m or NaN, or 1e-9 m bins, wrote all-zero scans and said 'wrote 1'."""
    for layout in (dict(range_resolution_m=0.175, range_offset_m=500.0),
                   dict(range_resolution_m=0.175, range_offset_m=199.5)):  # an overlap of half a metre
        with pytest.raises(ScanFormatError, match="overlap fewer than 64 range bins"):
            import_polar_scan(_foreign(), ForeignScanLayout(**layout), "boreas")
    with pytest.raises(ScanFormatError, match="1000 m behind the antenna"):  # refused as a layout (session 36)
        ForeignScanLayout(range_resolution_m=0.175, range_offset_m=-1000.0)
    with pytest.raises(ScanFormatError, match="finite"):
        ForeignScanLayout(0.175, float("nan"))
    with pytest.raises(ScanFormatError, match="not a radar's"):
        ForeignScanLayout(1e-9)
    turned = ForeignScanLayout(0.175, start_azimuth_rad=1e17)
    assert 0.0 <= turned.start_azimuth_rad < 2 * np.pi


def test_cli_never_overwrites_earlier_scans_nor_mixes_name_kinds(tmp_path):
    """QA (session 20): a second import into the same --out replaced its scans without a word, and 'scanA.png'
    became a 1970 scan among 2019 ones."""
    cv2.imwrite(str(tmp_path / "1566535872045000.png"), _foreign())
    assert _import(tmp_path, tmp_path / "1566535872045000.png").exit_code == 0
    first = (tmp_path / "o" / "1566535872045000.png").read_bytes()
    res = _import(tmp_path, tmp_path / "1566535872045000.png")
    assert res.exit_code == 2 and "--overwrite" in res.output
    assert (tmp_path / "o" / "1566535872045000.png").read_bytes() == first
    cv2.imwrite(str(tmp_path / "scanA.png"), _foreign())
    res = _import(tmp_path, tmp_path / "scanA.png", tmp_path / "1566535872045000.png", out="o2")
    assert res.exit_code == 2 and "mix" in res.output and not (tmp_path / "o2").exists()
    res = _import(tmp_path, tmp_path / "missing.png", out="o3")
    assert res.exit_code == 2 and "no such file" in res.output and "WARN" not in res.output
    res = _import(tmp_path, tmp_path, out="o3")
    assert res.exit_code == 2 and "is a folder" in res.output


def test_cli_orders_names_naturally_and_prints_the_mapping(tmp_path):
    """QA 8: scan_10 once came before scan_9 (text order) and nothing said which input got which timestamp."""
    for k in (1, 2, 9, 10, 11):
        cv2.imwrite(str(tmp_path / f"scan_{k}.png"), _foreign(peak_bin=40 + k))
    res = _import(tmp_path, *(tmp_path / f"scan_{k}.png" for k in (10, 9, 11, 2, 1)))
    assert res.exit_code == 0, res.output
    for k, seconds in ((1, 1), (2, 2), (9, 3), (10, 4), (11, 5)):
        assert f"scan_{k}.png -> {seconds}000000.png" in res.output
        # the scan itself went there: its peak bin (0.175 m/bin) is at (40 + k) * 0.175 m
        scan = load_scan(tmp_path / "o" / f"{seconds}000000.png", "boreas")
        peak_m = get_preset("boreas").range_offset_m + int(np.argmax(scan.power[0])) * 0.0596
        assert peak_m == pytest.approx((40 + k) * 0.175, abs=0.1)


def test_cli_refuses_a_scan_given_twice(tmp_path):
    """QA re-test (session 23): the same file given twice became two identical scans a second apart."""
    cv2.imwrite(str(tmp_path / "scan_1.png"), _foreign())
    res = _import(tmp_path, tmp_path / "scan_1.png", tmp_path / "." / "scan_1.png")
    assert res.exit_code != 0 and "given twice" in res.output
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_cli_prints_the_assumed_geometry_and_warns_on_a_likely_transposed_source(tmp_path):
    """QA 7: a 576 (range bins) x 400 (azimuths) image without --transposed was imported silently."""
    from reradar_core.cli_commands.import_scans import orientation_hint

    cv2.imwrite(str(tmp_path / "1600000000000000.png"), _foreign().T.copy())
    res = _import(tmp_path, tmp_path / "1600000000000000.png")
    assert res.exit_code == 0, res.output
    assert "576 azimuths x 400 range bins" in res.output and "maximum range 69.8 m" in res.output
    assert "pass --transposed" in res.output
    # the usual layout: geometry printed, no warning
    cv2.imwrite(str(tmp_path / "1600000000250000.png"), _foreign())
    res = _import(tmp_path, tmp_path / "1600000000250000.png", out="o2")
    assert res.exit_code == 0 and "400 azimuths x 576 range bins" in res.output and "warning" not in res.output
    assert orientation_hint((400, 576), transposed=False) is None
    assert "drop --transposed" in orientation_hint((400, 576), transposed=True)


def test_help_says_what_build_map_needs_besides_the_scans():
    """QA 15: the help promised `build-map --dataset` on the output, which lacks the radar/ folder and poses."""
    from reradar_cli import app

    res = CliRunner().invoke(app, ["import-scans", "--help"], env={"COLUMNS": "200"})
    assert res.exit_code == 0
    text = " ".join(res.output.split())
    assert "SEQ/radar/<t_us>.png" in text and "radar_poses.csv" in text and "natural" in text


def test_cli_refuses_a_truncated_png_in_one_line(tmp_path, capfd):
    """A truncated greyscale PNG is named as one, before libpng reads it (QA session 36: libpng printed its own
    "libpng error: Read Error" line first)."""
    power = (np.random.default_rng(0).random((64, 500)) * 255).astype(np.uint8)
    ok, png = cv2.imencode(".png", power)
    assert ok
    src = tmp_path / "1600000000000000.png"
    src.write_bytes(png.tobytes()[: len(png) // 2])
    res = _import(tmp_path, src)
    assert res.exit_code != 0 and "not a readable PNG image (corrupt or truncated)" in res.output
    assert "libpng" not in capfd.readouterr().err


def test_a_range_offset_far_behind_the_antenna_is_refused():
    """QA session 36: --range-offset -50 was accepted; a calibration shift (Boreas -0.31 m) still is."""
    with pytest.raises(ScanFormatError, match="50 m behind the antenna"):
        ForeignScanLayout(0.175, -50.0)
    assert ForeignScanLayout(0.0596, -0.31).range_offset_m == -0.31


def test_cli_writes_nothing_when_a_later_source_is_refused(tmp_path):
    """QA session 38: the scans before a refused source stayed in --out, and the re-run after the fix was refused for
    them; the odd names of a mix are named."""
    cv2.imwrite(str(tmp_path / "1566535872045000.png"), _foreign())
    cv2.imwrite(str(tmp_path / "1566535872295000.png"), np.dstack([_foreign()] * 3))  # colour: refused
    res = _import(tmp_path, tmp_path / "1566535872045000.png", tmp_path / "1566535872295000.png")
    assert res.exit_code == 2 and "3-channel colour image" in res.output and "nothing was written" in res.output
    assert not (tmp_path / "o").exists()
    (tmp_path / "o2").mkdir()
    (tmp_path / "o2" / "keep.txt").write_text("x")
    res = _import(tmp_path, tmp_path / "1566535872045000.png", tmp_path / "1566535872295000.png", out="o2")
    assert res.exit_code == 2 and sorted(p.name for p in (tmp_path / "o2").iterdir()) == ["keep.txt"]
    cv2.imwrite(str(tmp_path / "1566535872545000 (1).png"), _foreign())
    res = _import(tmp_path, tmp_path / "1566535872045000.png", tmp_path / "1566535872545000 (1).png", out="o3")
    assert res.exit_code == 2 and "1566535872545000 (1).png" in res.output and "1 with other names" in res.output


def test_a_png_declaring_a_huge_image_is_refused_before_decoding(tmp_path):
    """QA session 38: a 74-byte PNG declaring 100,000 x 100,000 pixels ended in OpenCV's traceback (info,
    import-scans, build-map)."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 100_000, 100_000, 8, 0, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(b"\0" * 10)) + chunk(b"IEND", b""))
    (tmp_path / "1566535872045000.png").write_bytes(png)
    with pytest.raises(ScanFormatError, match="declares 100000 x 100000 pixels"):
        load_scan(tmp_path / "1566535872045000.png", "boreas")
    res = _import(tmp_path, tmp_path / "1566535872045000.png")
    assert res.exit_code == 2 and "declares 100000 x 100000 pixels" in res.output and "Traceback" not in res.output
