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
    (tmp_path / "empty.png").write_bytes(b"")  # QA session 40: an OpenCV assertion in a traceback, exit 1
    res = _import(tmp_path, tmp_path / "empty.png")
    assert res.exit_code == 2 and "empty.png: empty file (0 bytes)" in res.output and "Traceback" not in res.output


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


# ---- --bit-depth: integer samples that do not fill their type (12-bit data in a 16-bit PNG) ---------------------


def test_full_scale_of_a_bit_depth():
    from reradar_core.cli_commands.import_scans import full_scale

    assert [full_scale(b) for b in (1, 8, 10, 12, 16)] == [1, 255, 1023, 4095, 65535]
    for bad in (0, 17):
        with pytest.raises(ScanFormatError, match="1 to 16"):
            full_scale(bad)


@pytest.mark.parametrize(("raw", "bit_depth", "power"), [
    # value / (2^bits - 1), by hand
    (np.array([[0, 1365, 2730, 4095]], np.uint16), 12, [0.0, 1 / 3, 2 / 3, 1.0]),
    (np.array([[0, 341, 682, 1023]], np.uint16), 10, [0.0, 1 / 3, 2 / 3, 1.0]),
    (np.array([[0, 51, 255, 128]], np.uint16), 8, [0.0, 0.2, 1.0, 128 / 255]),  # 8-bit data in a 16-bit PNG
    (np.array([[0, 51, 255, 17]], np.uint8), 8, [0.0, 0.2, 1.0, 1 / 15]),
    (np.array([[0, 13107, 65535, 1]], np.uint16), 16, [0.0, 0.2, 1.0, 1 / 65535]),
    (np.array([[0, 1365, 4095, 0]], np.int32), 12, [0.0, 1 / 3, 1.0, 0.0]),  # an integer .npy
])
def test_bit_depth_scales_samples_to_unit_power(raw, bit_depth, power):
    from reradar_core.cli_commands.import_scans import scale_to_unit_power

    out = scale_to_unit_power(raw, "s.png", bit_depth)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, np.array([power], np.float32))


@pytest.mark.parametrize(("raw", "bit_depth", "from_png", "message"), [
    (np.array([[0, 4096]], np.uint16), 12, True,
     "s.png: a sample reaches 4096, above the 12-bit full scale 4095 (--bit-depth 12): the samples have more bits; "
     "pass the radar's sample depth (at least --bit-depth 13)"),
    (np.array([[0, 256]], np.uint16), 8, True, "at least --bit-depth 9"),
    (np.array([[0, 200]], np.uint8), 12, True,
     "s.png: the PNG has 8 bits per sample, too few for 12-bit samples (--bit-depth 12): pass --bit-depth 8 "
     "or less"),
    (np.array([[0, 200]], np.int16), 16, False, "the array (int16) holds at most 15 bits per sample, too few for 16-bit samples"),
    (np.array([[0.0, 0.5]], np.float32), 12, False, "holds float32 samples; --bit-depth scales integer samples"),
    (np.array([[-3, 5]], np.int16), 12, False, "a sample is -3; radar power is not negative"),
])
def test_bit_depth_refuses_samples_it_cannot_hold(raw, bit_depth, from_png, message):
    from reradar_core.cli_commands.import_scans import scale_to_unit_power

    with pytest.raises(ScanFormatError) as exc:
        scale_to_unit_power(raw, "s.png", bit_depth, from_png=from_png)
    assert message in str(exc.value)


def test_without_bit_depth_samples_are_read_as_before(caplog):
    """16-bit PNGs at 65535 (a warning that now names --bit-depth when they reach 12 bits or fewer), uint8 and
    floats left to the importer; an integer .npy above 1 is refused naming --bit-depth (it was refused before,
    asking to rescale)."""
    from reradar_core.cli_commands.import_scans import scale_to_unit_power

    full = np.array([[0, 13107, 65535]], np.uint16)
    np.testing.assert_array_equal(scale_to_unit_power(full, "a.png"), np.array([[0.0, 0.2, 1.0]], np.float32))
    assert "bit-depth" not in caplog.text
    twelve = np.array([[0, 4095]], np.uint16)
    with caplog.at_level("WARNING"):
        np.testing.assert_array_equal(scale_to_unit_power(twelve, "b.png"),
                                      np.array([[0.0, 4095 / 65535]], np.float32))
    assert "b.png: a 16-bit PNG whose values reach only 4095" in caplog.text
    assert "--bit-depth 12 (full scale 4095)" in caplog.text
    byte = np.array([[0, 255]], np.uint8)
    assert scale_to_unit_power(byte, "c.png") is byte
    floats = np.array([[0.0, 0.5]], np.float32)
    assert scale_to_unit_power(floats, "d.npy", from_png=False) is floats
    with pytest.raises(ScanFormatError, match=r"e.npy: integer samples up to 4095 \(uint16\) with no stated full "
                                              r"scale: pass the radar's sample depth, e.g. --bit-depth 12"):
        scale_to_unit_power(twelve, "e.npy", from_png=False)


def _uniform_16bit(path, value: int, n_az: int = 400, n_bins: int = 576):
    """A 16-bit greyscale PNG (or uint16 .npy) of ``value`` everywhere: 0.175 m bins reach 100.6 m."""
    arr = np.full((n_az, n_bins), value, np.uint16)
    if path.suffix == ".npy":
        np.save(path, arr)
    else:
        assert cv2.imwrite(str(path), arr)
    return path


def _import_with(tmp_path, *sources, bit_depth=None, out="o"):
    from reradar_cli import app

    extra = [] if bit_depth is None else ["--bit-depth", str(bit_depth)]
    return CliRunner().invoke(app, ["import-scans", *map(str, sources), "--out", str(tmp_path / out),
                                    "--range-resolution", "0.175", *extra])


def _inside_power(path):
    """The distinct power levels of an imported Boreas scan within the source's 0..100.6 m."""
    scan = load_scan(path, "boreas")
    inside = (scan.ranges_m >= 0.0) & (scan.ranges_m <= 100.5)
    assert np.all(scan.power[:, scan.ranges_m > 100.8] == 0)  # beyond the source: no return
    return np.unique(scan.power[:, inside])


@pytest.mark.parametrize("suffix", [".png", ".npy"])
def test_cli_bit_depth_12_reads_12_bit_samples_at_full_scale_4095(tmp_path, suffix):
    """1365 of 4095 is power 1/3, written as 85 of 255 in the Navtech PNG (at 65535 it was 5 of 255)."""
    src = _uniform_16bit(tmp_path / f"1600000000000000{suffix}", 1365)
    res = _import_with(tmp_path, src, bit_depth=12)
    assert res.exit_code == 0, res.output
    assert "power read as 12-bit samples: value / 4095 (--bit-depth)" in res.output
    np.testing.assert_array_equal(_inside_power(tmp_path / "o" / "1600000000000000.png"),
                                  np.array([85 / 255], np.float32))


def test_cli_without_bit_depth_reads_a_16_bit_png_at_65535_and_names_the_option(tmp_path, caplog):
    src = _uniform_16bit(tmp_path / "1600000000000000.png", 1365)
    with caplog.at_level("WARNING"):
        res = _import_with(tmp_path, src)
    assert res.exit_code == 0, res.output
    assert "pass its sample depth, e.g. --bit-depth 12" in caplog.text
    # 1365 / 65535 * 255 = 5.3 -> 5
    np.testing.assert_array_equal(_inside_power(tmp_path / "o" / "1600000000000000.png"),
                                  np.array([5 / 255], np.float32))


def test_cli_refuses_a_sample_above_the_declared_full_scale_and_writes_nothing(tmp_path):
    """The first source fits 12 bits, the second reaches 5000: refused in one line naming the file and the depth
    it needs, and --out is left as it was (not created)."""
    good = _uniform_16bit(tmp_path / "1600000000000000.png", 1365)
    bad = np.full((400, 576), 1365, np.uint16)
    bad[7, 100] = 5000
    assert cv2.imwrite(str(tmp_path / "1600000000250000.png"), bad)
    res = _import_with(tmp_path, good, tmp_path / "1600000000250000.png", bit_depth=12)
    assert res.exit_code == 2, res.output
    assert ("error: 1600000000250000.png: a sample reaches 5000, above the 12-bit full scale 4095 (--bit-depth 12)"
            in res.output)
    assert "at least --bit-depth 13" in res.output and "nothing was written" in res.output
    assert "Traceback" not in res.output and str(tmp_path / "o" / ".reradar") not in res.output
    assert not (tmp_path / "o").exists()


def test_cli_refuses_impossible_bit_depths(tmp_path):
    cv2.imwrite(str(tmp_path / "1600000000000000.png"), _foreign())  # an 8-bit PNG
    res = _import_with(tmp_path, tmp_path / "1600000000000000.png", bit_depth=12)
    assert res.exit_code == 2 and "the PNG has 8 bits per sample, too few for 12-bit" in res.output
    assert not (tmp_path / "o").exists()
    res = _import_with(tmp_path, tmp_path / "1600000000000000.png", bit_depth=8)  # the same as without it
    assert res.exit_code == 0, res.output
    np.save(tmp_path / "f.npy", np.full((400, 576), 0.5, np.float32))
    res = _import_with(tmp_path, tmp_path / "f.npy", bit_depth=12, out="o2")
    assert res.exit_code == 2 and "drop --bit-depth for power already in [0, 1]" in res.output
    res = _import_with(tmp_path, tmp_path / "1600000000000000.png", bit_depth=17, out="o3")
    assert res.exit_code == 2 and "'--bit-depth': Input should be less than or equal to 16" in res.output
    assert not (tmp_path / "o2").exists() and not (tmp_path / "o3").exists()


def test_help_documents_bit_depth():
    from reradar_cli import app

    res = CliRunner().invoke(app, ["import-scans", "--help"], env={"COLUMNS": "200"})
    text = " ".join(res.output.split())
    assert res.exit_code == 0 and "--bit-depth N reads integer samples as value / (2^N - 1)" in text
    assert "12 for 12-bit data in a 16-bit PNG (4095 = full power)" in text
