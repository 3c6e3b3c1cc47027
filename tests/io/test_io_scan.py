"""Navtech PNG / .npy scan I/O: exact round trips and clear errors on bad input."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from reradar_core.errors import ScanFormatError
from reradar_core.io.presets import ENCODER_TICKS_PER_TURN
from reradar_core.io.scan import (
    NAVTECH_META_COLUMNS,
    RadarScan,
    decode_navtech_png_bytes,
    encode_navtech_png_bytes,
    load_scan,
    load_scan_bytes,
    read_navtech_png,
    read_npy_header,
    read_png_header,
    read_polar_npy,
    scan_header,
    sniff_scan_format,
    write_navtech_png,
)

N_AZ, N_BINS = 16, 3768  # Oxford bin count so the preset is inferred from the width


def _quantised_scan(seed: int = 0, n_bins: int = N_BINS) -> RadarScan:
    """A scan whose power is exactly representable in the PNG (k / 255) and whose azimuths are on encoder ticks."""
    rng = np.random.default_rng(seed)
    power = rng.integers(0, 256, size=(N_AZ, n_bins)).astype(np.float32) / 255.0
    encoder = (np.arange(N_AZ) * (ENCODER_TICKS_PER_TURN // N_AZ) + 7) % ENCODER_TICKS_PER_TURN
    azimuths = encoder * (2 * np.pi / ENCODER_TICKS_PER_TURN)
    timestamps = 1547131046353776 + np.arange(N_AZ, dtype=np.int64) * 625
    valid = np.ones(N_AZ, dtype=bool)
    valid[3] = False
    return RadarScan(power, azimuths, timestamps, 0.0432, 0.0, valid, preset="oxford")


def _assert_same(a: RadarScan, b: RadarScan) -> None:
    np.testing.assert_array_equal(a.power, b.power)
    np.testing.assert_allclose(a.azimuths, b.azimuths, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(a.timestamps_us, b.timestamps_us)
    np.testing.assert_array_equal(a.valid, b.valid)
    assert a.range_resolution_m == b.range_resolution_m
    assert a.range_offset_m == b.range_offset_m


def test_png_file_round_trip_is_exact(tmp_path):
    scan = _quantised_scan()
    path = write_navtech_png(scan, tmp_path / "sub" / f"{scan.timestamp_us}.png")
    back = read_navtech_png(path)
    _assert_same(scan, back)
    assert back.preset == "oxford"
    assert back.timestamp_us == 1547131046353776
    assert back.power.dtype == np.float32


def test_png_bytes_round_trip_and_load_helpers(tmp_path):
    scan = _quantised_scan(1)
    data = encode_navtech_png_bytes(scan)
    _assert_same(scan, decode_navtech_png_bytes(data))
    _assert_same(scan, load_scan_bytes(data, "upload.png"))
    path = write_navtech_png(scan, tmp_path / "s.png")
    _assert_same(scan, load_scan(path))


def test_png_byte_layout_matches_navtech(tmp_path):
    """Columns 0-7 int64 timestamp, 8-9 uint16 encoder, 10 valid, then power bytes."""
    scan = _quantised_scan(2)
    path = write_navtech_png(scan, tmp_path / "s.png")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint8 and raw.shape == (N_AZ, NAVTECH_META_COLUMNS + N_BINS)
    ts = raw[:, :8].copy().view("<i8").ravel()
    enc = raw[:, 8:10].copy().view("<u2").ravel()
    np.testing.assert_array_equal(ts, scan.timestamps_us)
    np.testing.assert_array_equal(enc, np.round(scan.azimuths / (2 * np.pi / ENCODER_TICKS_PER_TURN)))
    assert raw[3, 10] == 0 and raw[0, 10] != 0
    np.testing.assert_array_equal(raw[:, 11:], np.round(scan.power * 255).astype(np.uint8))


def test_boreas_width_is_ambiguous_without_a_preset(tmp_path):
    """3,360 bins are Boreas, Boreas-2021 or MulRan (0.0596 / 0.04381 / 0.0595 m per bin): never guessed."""
    path = write_navtech_png(_quantised_scan(3, n_bins=3360), tmp_path / "b.png")
    with pytest.raises(ScanFormatError, match="3360 range bins fit several radar presets.*boreas.*mulran.*--preset"):
        read_navtech_png(path)
    back = read_navtech_png(path, "boreas")
    assert back.preset == "boreas"
    assert back.range_resolution_m == pytest.approx(0.0596)
    assert back.range_offset_m == pytest.approx(-0.31)
    mulran = load_scan(path, "mulran")
    assert (mulran.preset, mulran.range_resolution_m, mulran.range_offset_m) == ("mulran", 0.0595, 0.0)


def test_npy_uint8_and_float(tmp_path):
    rng = np.random.default_rng(4)
    arr8 = rng.integers(0, 256, size=(400, 3768), dtype=np.uint8)
    np.save(tmp_path / "a.npy", arr8)
    scan = load_scan(tmp_path / "a.npy")
    np.testing.assert_array_equal(scan.power, arr8.astype(np.float32) / 255.0)
    assert scan.num_azimuths == 400
    np.testing.assert_allclose(np.diff(scan.azimuths), 2 * np.pi / 400)
    arrf = rng.random((400, 3360), dtype=np.float32)
    np.save(tmp_path / "b.npy", arrf)
    scan_b = read_polar_npy(tmp_path / "b.npy", preset="boreas")
    np.testing.assert_array_equal(scan_b.power, arrf)
    assert scan_b.range_resolution_m == pytest.approx(0.0596)


def test_truncated_png_is_refused_before_libpng_prints(tmp_path, capfd):
    """Session 21: libpng printed its own error line on stderr (outside our logs) for a truncated PNG before our
    message; the chunk walk refuses it first, for uploads and for files."""
    from reradar_core.io.scan import png_incomplete

    data = encode_navtech_png_bytes(_quantised_scan())
    assert not png_incomplete(data)
    for cut in (len(data) // 2, len(data) - 5, 9):
        assert png_incomplete(data[:cut])
        with pytest.raises(ScanFormatError, match="corrupt or truncated"):
            decode_navtech_png_bytes(data[:cut])
        (tmp_path / "cut.png").write_bytes(data[:cut])
        with pytest.raises(ScanFormatError, match="cut.png: not a readable PNG image"):
            read_navtech_png(tmp_path / "cut.png")
    out, err = capfd.readouterr()
    assert "libpng" not in err + out and "incomplete" not in err + out


def test_corrupt_png_bytes_raise_scan_format_error():
    data = encode_navtech_png_bytes(_quantised_scan())
    with pytest.raises(ScanFormatError, match="corrupt or truncated"):
        decode_navtech_png_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(ScanFormatError, match="corrupt or truncated"):
        decode_navtech_png_bytes(data[:40])
    with pytest.raises(ScanFormatError):
        decode_navtech_png_bytes(b"")


def test_16bit_png_rejected_with_reason(tmp_path):
    img = np.zeros((8, NAVTECH_META_COLUMNS + 3768), dtype=np.uint16)
    path = tmp_path / "deep.png"
    assert cv2.imwrite(str(path), img)
    with pytest.raises(ScanFormatError, match="8-bit") as info:
        read_navtech_png(path)
    assert "deep.png" in str(info.value)


def test_colour_png_rejected(tmp_path):
    path = tmp_path / "rgb.png"
    cv2.imwrite(str(path), np.zeros((8, 3779, 3), dtype=np.uint8))
    with pytest.raises(ScanFormatError, match="single-channel"):
        read_navtech_png(path)


def test_wrong_shapes_rejected(tmp_path):
    path = tmp_path / "narrow.png"
    cv2.imwrite(str(path), np.zeros((8, NAVTECH_META_COLUMNS), dtype=np.uint8))
    with pytest.raises(ScanFormatError, match="metadata"):
        read_navtech_png(path)
    path2 = tmp_path / "odd.png"
    cv2.imwrite(str(path2), np.zeros((8, NAVTECH_META_COLUMNS + 1000), dtype=np.uint8))
    with pytest.raises(ScanFormatError, match="cannot infer the radar preset"):
        read_navtech_png(path2)
    with pytest.raises(ScanFormatError, match="2-D"):
        RadarScan(np.zeros(10), np.zeros(10), np.zeros(10), 0.04)
    with pytest.raises(ScanFormatError, match="azimuths must have shape"):
        RadarScan(np.zeros((4, 10)), np.zeros(3), np.zeros(4), 0.04)
    with pytest.raises(ScanFormatError, match="2-D"):
        read_polar_npy(array=np.zeros((3, 4, 5), dtype=np.uint8))


def test_nan_power_rejected(tmp_path):
    power = np.zeros((4, 10), dtype=np.float32)
    power[1, 2] = np.nan
    with pytest.raises(ScanFormatError, match="NaN"):
        RadarScan(power, np.zeros(4), np.zeros(4), 0.04)
    arr = np.zeros((400, 3768), dtype=np.float32)
    arr[0, 0] = np.nan
    np.save(tmp_path / "nan.npy", arr)
    with pytest.raises(ScanFormatError, match="NaN"):
        load_scan(tmp_path / "nan.npy")


def test_power_outside_zero_one_is_refused_with_a_hint():
    az = np.arange(4) * np.pi / 2
    with pytest.raises(ScanFormatError, match=r"\[0, 1\].*divide by 255"):
        RadarScan(np.full((4, 10), 200.0), az, np.zeros(4), 0.04)  # 8-bit values given as float
    with pytest.raises(ScanFormatError, match=r"\[0, 1\]"):
        RadarScan(np.full((4, 10), -0.5), az, np.zeros(4), 0.04)
    # the scale's own ends and float rounding of value / 255 pass
    RadarScan(np.array([[0.0, 1.0], [1.0 + 1e-6, 0.5]]), az[:2], np.zeros(2), 0.04)


def test_azimuths_in_degrees_are_refused():
    deg = np.arange(400) * 0.9  # 0 ... 359.1: degrees, which the Cartesian image would read as 0.9 rad steps
    with pytest.raises(ScanFormatError, match="degrees"):
        RadarScan(np.zeros((400, 10)), deg, np.zeros(400), 0.04)
    # radians in (-pi, pi] (another convention) keep working: the image is located from the first azimuth
    RadarScan(np.zeros((400, 10)), np.arange(400) * 2 * np.pi / 400 - np.pi, np.zeros(400), 0.04)


def test_missing_and_unsupported_files(tmp_path):
    with pytest.raises(ScanFormatError, match="no such scan file"):
        read_navtech_png(tmp_path / "missing.png")
    (tmp_path / "2500000.png").mkdir()  # a folder named like a scan (QA, session 24): said so
    with pytest.raises(ScanFormatError, match="2500000.png: is a folder, not a scan file"):
        read_navtech_png(tmp_path / "2500000.png")
    (tmp_path / "x.jpg").write_bytes(b"123")
    with pytest.raises(ScanFormatError, match="unsupported scan format"):
        load_scan(tmp_path / "x.jpg")
    (tmp_path / "bad.npy").write_bytes(b"not numpy")
    with pytest.raises(ScanFormatError, match="not a readable .npy"):
        load_scan(tmp_path / "bad.npy")
    with pytest.raises(ScanFormatError, match="not a readable .npy"):
        load_scan_bytes(b"not numpy", "scan.npy")
    with pytest.raises(ScanFormatError, match=r"\[0, 1\]"):
        read_polar_npy(array=np.full((400, 3768), 2.0, dtype=np.float32))


def _npy_bytes(arr: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, arr)
    return buf.getvalue()


def test_png_header_gives_shape_without_decoding():
    data = encode_navtech_png_bytes(_quantised_scan())
    header = read_png_header(data)
    assert header.format == "png" and header.shape == (N_AZ, NAVTECH_META_COLUMNS + N_BINS)
    assert header.itemsize == 1 and header.decoded_bytes == N_AZ * (NAVTECH_META_COLUMNS + N_BINS)
    assert scan_header(data[:64], size=len(data)) == header  # the first bytes are enough
    ok, deep = cv2.imencode(".png", np.zeros((8, 40), np.uint16))
    with pytest.raises(ScanFormatError, match="16-bit"):
        read_png_header(deep.tobytes())
    ok, rgb = cv2.imencode(".png", np.zeros((8, 40, 3), np.uint8))
    with pytest.raises(ScanFormatError, match="colour"):
        read_png_header(rgb.tobytes())
    with pytest.raises(ScanFormatError, match="truncated"):
        read_png_header(data[:20])
    with pytest.raises(ScanFormatError, match="no PNG signature"):
        read_png_header(b"GIF89a" + data[6:])


def test_npy_header_gives_shape_and_refuses_lies():
    arr = np.zeros((400, 3768), np.float32)
    data = _npy_bytes(arr)
    header = read_npy_header(data)
    assert header.shape == (400, 3768) and header.itemsize == 4 and header.dtype == "<f4"
    assert scan_header(data[:200], size=len(data)).shape == (400, 3768)
    with pytest.raises(ScanFormatError, match="shorter"):
        read_npy_header(data[: len(data) // 2])  # header says more data than the file holds
    with pytest.raises(ScanFormatError, match="2-D"):
        read_npy_header(_npy_bytes(np.zeros((2, 3, 4), np.uint8)))
    with pytest.raises(ScanFormatError, match="numeric"):
        read_npy_header(_npy_bytes(np.array([["a", "b"]])))
    with pytest.raises(ScanFormatError, match="C-ordered"):
        read_npy_header(_npy_bytes(np.asfortranarray(np.zeros((70, 80), np.uint8))))
    with pytest.raises(ScanFormatError, match="not a readable .npy"):
        read_npy_header(b"\x93NUMPY\x01\x00\xff\xff garbage")


def test_lossy_and_unknown_formats_are_named():
    ok, jpg = cv2.imencode(".jpg", np.zeros((64, 64), np.uint8))
    assert sniff_scan_format(jpg.tobytes()) == "jpeg"
    assert sniff_scan_format(b"RIFF\x00\x00\x00\x00WEBPVP8 ") == "webp"
    assert sniff_scan_format(encode_navtech_png_bytes(_quantised_scan())) == "png"
    with pytest.raises(ScanFormatError, match="JPEG images are lossy"):
        scan_header(jpg.tobytes())
    with pytest.raises(ScanFormatError, match="GIF images are palette-quantised"):  # lossless, but not a scan
        scan_header(b"GIF89a" + bytes(64))
    with pytest.raises(ScanFormatError, match="unrecognised"):
        scan_header(b"hello world")
    with pytest.raises(ScanFormatError, match="empty"):
        scan_header(b"")
    with pytest.raises(ScanFormatError, match="corrupt or truncated"):
        decode_navtech_png_bytes(jpg.tobytes())  # OpenCV would decode it: the PNG signature is required


def test_navtech_npy_decodes_to_the_pngs_scan() -> None:
    import io

    from reradar_core.io.scan import decode_navtech_npy_bytes, load_scan_bytes

    rng = np.random.default_rng(3)
    scan = RadarScan.from_power(rng.uniform(0, 1, (400, 3360)).astype(np.float32), "boreas")
    png = encode_navtech_png_bytes(scan)
    buf = io.BytesIO()
    np.save(buf, cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED))
    a, b = decode_navtech_png_bytes(png), load_scan_bytes(buf.getvalue(), "x.npy", npy_layout="navtech")
    for name in ("power", "azimuths", "timestamps_us", "valid"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert (a.preset, a.range_resolution_m) == (b.preset, b.range_resolution_m)
    bad = io.BytesIO()
    np.save(bad, np.zeros((400, 3371), np.float32))
    with pytest.raises(ScanFormatError, match="uint8"):
        decode_navtech_npy_bytes(bad.getvalue())


def test_npy_preset_is_inferred_only_when_the_bin_count_names_one(tmp_path):
    """M1: a polar .npy gets the geometry its width names (3,768 -> oxford), refuses to guess between the 3,360-bin
    presets, and is read with an explicit preset exactly as asked (known bin sizes)."""
    rng = np.random.default_rng(5)
    np.save(tmp_path / "o.npy", rng.integers(0, 256, (400, 3768), dtype=np.uint8))
    assert load_scan(tmp_path / "o.npy").preset == "oxford"
    np.save(tmp_path / "b.npy", rng.integers(0, 256, (400, 3360), dtype=np.uint8))
    with pytest.raises(ScanFormatError, match="3360 range bins fit several radar presets.*--preset"):
        load_scan(tmp_path / "b.npy")
    for preset, resolution, offset in (("boreas", 0.0596, -0.31), ("mulran", 0.0595, 0.0)):
        scan = load_scan(tmp_path / "b.npy", preset)
        assert (scan.preset, scan.range_resolution_m, scan.range_offset_m) == (preset, resolution, offset)


@pytest.mark.parametrize("shape, preset, match", [
    ((3360, 400), "boreas", "looks transposed"),
    ((400, 5000), "oxford", "5000 range bins, but preset 'oxford' has 3768"),
    ((3, 3), "oxford", "3 azimuths x 3 range bins; expected a full sweep with 64..8192"),
])
def test_npy_layout_contradicting_the_preset_is_refused(tmp_path, shape, preset, match):
    np.save(tmp_path / "s.npy", np.zeros(shape, np.uint8))
    with pytest.raises(ScanFormatError, match=match):
        load_scan(tmp_path / "s.npy", preset)
    # the upload path (service) applies the same check
    with pytest.raises(ScanFormatError, match=match):
        load_scan_bytes((tmp_path / "s.npy").read_bytes(), "s.npy", preset)


def test_navtech_metadata_is_recognised(tmp_path):
    from reradar_core.io.scan import has_navtech_metadata

    raw = cv2.imread(str(write_navtech_png(_quantised_scan(1), tmp_path / "n.png")), cv2.IMREAD_UNCHANGED)
    assert has_navtech_metadata(raw)
    assert not has_navtech_metadata(raw[:, NAVTECH_META_COLUMNS:].copy())  # the same power without metadata
    assert not has_navtech_metadata(np.random.default_rng(0).integers(0, 256, (400, 600), dtype=np.uint8))


def test_upload_without_a_preset_takes_the_maps_where_the_scan_fits_it():
    """The service reads an upload sent without ``preset`` with the target map's preset when the bin count fits
    it (a 3,360-bin PNG on a Boreas-2021 map is 0.04381 m per bin, not the 0.0596 m of 2020's Boreas); a map
    whose preset has another bin count changes nothing; a polar .npy (no geometry of its own) takes the map's."""
    png = encode_navtech_png_bytes(_quantised_scan(4, n_bins=3360))
    assert load_scan_bytes(png, "q.png").preset == "boreas"  # no map: the API's documented default
    on_2021 = load_scan_bytes(png, "q.png", map_preset="boreas-2021")
    assert (on_2021.preset, on_2021.range_resolution_m) == ("boreas-2021", pytest.approx(0.04381))
    assert load_scan_bytes(png, "q.png", map_preset="oxford").preset == "boreas"  # 3768 bins: does not fit
    assert load_scan_bytes(png, "q.png", preset="mulran", map_preset="boreas-2021").preset == "mulran"  # asked
    polar = _npy_bytes(np.zeros((400, 3360), np.uint8))
    assert load_scan_bytes(polar, "q.npy").preset == "oxford"
    npy = load_scan_bytes(polar, "q.npy", map_preset="mulran")
    assert (npy.preset, npy.range_resolution_m) == ("mulran", pytest.approx(0.0595))


def test_a_navtech_image_sent_as_polar_gets_a_hint():
    """QA (session 21): an .npy of a Navtech image (11 metadata columns + 3,360 bins) sent as a polar array was
    refused with '3371 range bins, but preset boreas has 3360' and no word on scan_layout."""
    from reradar_core.io.presets import get_preset
    from reradar_core.io.scan import check_polar_shape, infer_preset

    with pytest.raises(ScanFormatError, match=r"3371 = 11 metadata columns \+ 3360 range bins.*scan_layout=navtech"):
        check_polar_shape(400, 3371, get_preset("boreas"), "q.npy")
    with pytest.raises(ScanFormatError, match=r"--scan-layout navtech"):
        infer_preset(3779, "q.npy")  # 11 + 3768 (oxford)
    with pytest.raises(ScanFormatError) as exc:
        infer_preset(3000, "q.npy")
    assert "navtech" not in str(exc.value)


def test_npy_with_bytes_after_its_data_is_refused():
    """An .npy whose file holds more than its header declares (two files joined, a header that lies) is refused,
    as one holding less is (QA session 36: 1 MB appended to a scan was localized)."""
    data = _npy_bytes(np.zeros((400, 3360), np.uint8))
    with pytest.raises(ScanFormatError, match="1,048,576 more bytes follow"):
        read_npy_header(data + b"\xff" * (1 << 20))
    with pytest.raises(ScanFormatError, match="1 more byte follows"):  # the upload path: header bytes plus the size
        scan_header(data[:200], size=len(data) + 1)
    assert read_npy_header(data).shape == (400, 3360)


def test_transposed_navtech_png_is_said_to_be_transposed():
    """A Navtech PNG saved transposed (3,371 rows x 400 columns) is named as transposed, not "cannot infer the
    radar preset from 389 range bins" (QA session 36); with a preset given the layout check says so too."""
    scan = np.zeros((400, 3360 + NAVTECH_META_COLUMNS), np.uint8)
    scan[:, :8] = np.frombuffer(np.arange(400, dtype="<i8").tobytes(), np.uint8).reshape(400, 8)
    ok, png = cv2.imencode(".png", np.ascontiguousarray(scan.T))
    assert ok
    with pytest.raises(ScanFormatError, match="3371 rows x 400 columns.*looks transposed"):
        load_scan_bytes(png.tobytes(), "scan.png")
    with pytest.raises(ScanFormatError, match="transposed"):
        load_scan_bytes(png.tobytes(), "scan.png", "boreas")


def test_png_with_a_corrupt_chunk_is_refused_before_libpng_reads_it(tmp_path, capfd):
    """A PNG with a flipped byte (a chunk CRC error) is one clean error, without libpng's own "IDAT: CRC error" line
    (QA session 36)."""
    path = tmp_path / "1547131046353776.png"
    write_navtech_png(_quantised_scan(), path)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ScanFormatError, match="IDAT chunk fails its checksum"):
        load_scan(path)
    assert "libpng" not in capfd.readouterr().err

