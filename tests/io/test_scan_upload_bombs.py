"""Uploaded scans that cost more than they declare (QA session 21): PNG decompression bombs are refused before
libpng inflates them, the rows of plain PNGs are decoded without inflating twice (the same pixels as libpng), and
Navtech timestamps that are no time (negative, decreasing, beyond 2^62) are refused with the problem named."""

from __future__ import annotations

import struct
import types
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

import reradar_core.io.scan as scan_io
from reradar_core.errors import ScanFormatError
from reradar_core.io.scan import (
    MAX_PNG_CHUNKS,
    MAX_PNG_TEXT_BYTES,
    MAX_SCAN_TIMESTAMP_US,
    NAVTECH_META_COLUMNS,
    RadarScan,
    check_png_image_data,
    decode_navtech_npy_bytes,
    decode_navtech_png_bytes,
    encode_navtech_png_bytes,
    png_image_data_size,
    read_navtech_png,
)

N_AZ, N_BINS = 64, 3360  # boreas bins: 3,371 columns with the metadata
T0_US = 1_600_000_000_000_000
DEMO_QUERIES = Path(__file__).resolve().parents[2] / "maps" / "demo" / "queries"
REAL_OXFORD = Path("/work/shared/data/real-oxford/radar")


def _navtech_pixels(seed: int = 0) -> np.ndarray:
    """(N_AZ, 11 + N_BINS) uint8 pixels of a valid Navtech scan with random power."""
    rng = np.random.default_rng(seed)
    scan = RadarScan.from_power(rng.integers(0, 256, (N_AZ, N_BINS), dtype=np.uint8), "boreas", T0_US)
    raw = cv2.imdecode(np.frombuffer(encode_navtech_png_bytes(scan), np.uint8), cv2.IMREAD_UNCHANGED)
    assert raw.shape == (N_AZ, NAVTECH_META_COLUMNS + N_BINS)
    return raw


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _filtered(rows: np.ndarray, filters: Sequence[int]) -> bytes:
    """PNG scanlines (filter byte + filtered bytes) of 8-bit greyscale ``rows`` (1 byte per pixel)."""
    out = []
    prev = np.zeros(rows.shape[1], np.int16)
    for row, kind in zip(rows.astype(np.int16), filters, strict=True):
        left = np.concatenate([[0], row[:-1]]).astype(np.int16)
        up_left = np.concatenate([[0], prev[:-1]]).astype(np.int16)
        if kind == 0:
            pred = np.zeros_like(row)
        elif kind == 1:
            pred = left
        elif kind == 2:
            pred = prev
        elif kind == 3:
            pred = (left + prev) // 2
        else:  # Paeth
            p = left + prev - up_left
            pa, pb, pc = np.abs(p - left), np.abs(p - prev), np.abs(p - up_left)
            pred = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, prev, up_left))
        out.append(bytes([kind]) + ((row - pred) % 256).astype(np.uint8).tobytes())
        prev = row
    return b"".join(out)


def _png(pixels: np.ndarray, filters: Sequence[int] | None = None, after_rows: bytes = b"", idat_split: int = 0,
         extra_chunks: Sequence[bytes] = (), interlaced: bool = False, declared_height: int | None = None) -> bytes:
    """A greyscale 8-bit PNG of ``pixels`` built by hand: rows filtered by ``filters`` (default None), then
    ``after_rows`` in the same zlib stream (a bomb's zeros), split into IDAT chunks of ``idat_split`` bytes;
    the IHDR may declare another height."""
    h, w = pixels.shape
    if interlaced:  # Adam7: each pass's sub-image, rows unfiltered
        raw = b"".join(_filtered(pixels[y0::dy, x0::dx], [0] * len(pixels[y0::dy, x0::dx]))
                       for x0, y0, dx, dy in scan_io._ADAM7_PASSES if pixels[y0::dy, x0::dx].size)
    else:
        raw = _filtered(pixels, filters if filters is not None else [0] * h)
    assert len(raw) == png_image_data_size(w, h, 8, 0, interlaced)
    packer = zlib.compressobj(9)
    stream = packer.compress(raw) + packer.compress(after_rows) + packer.flush()
    parts = [stream[i:i + idat_split] for i in range(0, len(stream), idat_split)] if idat_split else [stream]
    ihdr = struct.pack(">IIBBBBB", w, declared_height or h, 8, 0, 0, 0, int(interlaced))
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + b"".join(extra_chunks)
            + b"".join(_chunk(b"IDAT", p) for p in parts) + _chunk(b"IEND", b""))


class _CountingInflater:
    """``zlib.decompressobj()`` that adds up what it inflates."""

    total = 0

    def __init__(self) -> None:
        self._inflater = zlib.decompressobj()

    def decompress(self, data: Any, max_length: int = 0) -> bytes:
        out = self._inflater.decompress(data, max_length)
        _CountingInflater.total += len(out)
        return out

    @property
    def eof(self) -> bool:
        return self._inflater.eof

    @property
    def unconsumed_tail(self) -> bytes:
        return self._inflater.unconsumed_tail


@pytest.fixture
def inflated(monkeypatch: pytest.MonkeyPatch) -> type[_CountingInflater]:
    """Counts the bytes the scan module inflates; libpng must not see the file (``cv2.imdecode`` fails the test)."""
    _CountingInflater.total = 0
    monkeypatch.setattr(scan_io, "zlib", types.SimpleNamespace(decompressobj=_CountingInflater, error=zlib.error,
                                                                crc32=zlib.crc32))
    return _CountingInflater


def _no_libpng(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*_: object) -> None:
        raise AssertionError("cv2.imdecode was called")
    monkeypatch.setattr(cv2, "imdecode", refuse)


# ---- 1. IDAT bombs -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("idat_split", [0, 8192], ids=["one-idat", "8k-idats"])
def test_idat_bomb_is_refused_after_inflating_one_image(monkeypatch: pytest.MonkeyPatch, inflated,
                                                        idat_split: int) -> None:
    """The QA bomb in small: valid rows, then 4 MB of zeros in the same zlib stream (~4 kB compressed). It is
    refused naming the size the header declares, and inflating stops one byte past that size."""
    pixels = _navtech_pixels()
    expected = N_AZ * (1 + pixels.shape[1])
    bomb = _png(pixels, after_rows=b"\0" * (4 << 20), idat_split=idat_split)
    _no_libpng(monkeypatch)
    with pytest.raises(ScanFormatError, match="decompression bomb") as err:
        decode_navtech_png_bytes(bomb)
    assert f"{expected:,} bytes its {N_AZ} x {pixels.shape[1]} header declares" in str(err.value)
    assert inflated.total == expected + 1  # not one byte more than the header allows + 1
    with pytest.raises(ScanFormatError, match="decompression bomb"):
        check_png_image_data(bomb)


def test_one_extra_byte_after_the_rows_is_refused_and_the_exact_stream_is_decoded() -> None:
    pixels = _navtech_pixels()
    with pytest.raises(ScanFormatError, match="decompression bomb"):
        decode_navtech_png_bytes(_png(pixels, after_rows=b"\0"))
    scan = decode_navtech_png_bytes(_png(pixels))
    np.testing.assert_array_equal(scan.power, pixels[:, NAVTECH_META_COLUMNS:].astype(np.float32) / 255.0)


def test_short_or_corrupt_image_data_is_refused_before_libpng(monkeypatch: pytest.MonkeyPatch) -> None:
    pixels = _navtech_pixels()
    _no_libpng(monkeypatch)
    with pytest.raises(ScanFormatError, match=r"truncated: its image data ends after .* of the 215,808 bytes"):
        decode_navtech_png_bytes(_png(pixels[:-1], declared_height=N_AZ))
    good = _png(pixels)
    start = good.index(b"IDAT") + 4
    corrupt = good[:start] + b"\xff\xff\xff\xff" + good[start + 4:]  # the zlib header and first bytes
    with pytest.raises(ScanFormatError, match="corrupt compressed image data"):
        decode_navtech_png_bytes(corrupt)


def test_interlaced_png_size_is_the_sum_of_its_passes_and_a_bomb_is_refused() -> None:
    pixels = _navtech_pixels()
    h, w = pixels.shape
    passes = [(-(-(w - x0) // dx), -(-(h - y0) // dy)) for x0, y0, dx, dy in scan_io._ADAM7_PASSES]
    assert png_image_data_size(w, h, 8, 0, True) == sum(r * (1 + c) for c, r in passes if c > 0 and r > 0)
    assert png_image_data_size(1, 1, 8, 0, True) == 2  # passes 2-7 are empty for a single pixel
    assert png_image_data_size(3, 2, 16, 2, False) == 2 * (1 + 3 * 6)  # 16-bit RGB: 6 bytes a pixel
    assert png_image_data_size(5, 1, 1, 0, False) == 1 + 1  # 1-bit: 5 pixels in one byte
    scan = decode_navtech_png_bytes(_png(pixels, interlaced=True))  # libpng decodes it (not the plain path)
    np.testing.assert_array_equal(scan.power, pixels[:, NAVTECH_META_COLUMNS:].astype(np.float32) / 255.0)
    with pytest.raises(ScanFormatError, match="decompression bomb"):
        decode_navtech_png_bytes(_png(pixels, interlaced=True, after_rows=b"\0" * (1 << 20)))


def test_pngs_of_more_chunks_than_the_bound_are_refused_before_the_walks(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each chunk costs a step of the Python walks: 509,321 one-byte IDAT chunks took 1.9 s to check."""
    pixels = _navtech_pixels()
    stream_len = len(zlib.compress(_filtered(pixels, [0] * N_AZ), 9))
    split = -(-stream_len // (MAX_PNG_CHUNKS - 2))  # IHDR + IDATs + IEND: just within the bound
    scan = decode_navtech_png_bytes(_png(pixels, idat_split=split))
    np.testing.assert_array_equal(scan.power, pixels[:, NAVTECH_META_COLUMNS:].astype(np.float32) / 255.0)
    _no_libpng(monkeypatch)
    monkeypatch.setattr(scan_io, "png_incomplete", lambda _: pytest.fail("walked every chunk"))
    with pytest.raises(ScanFormatError, match="more than 10,000 chunks"):
        decode_navtech_png_bytes(_png(pixels, idat_split=max(1, stream_len // MAX_PNG_CHUNKS)))


# ---- text chunks: libpng inflates each zTXt up to 8 MB before the image -------------------------------------

def _ztxt(size: int) -> bytes:
    return _chunk(b"zTXt", b"Comment\0\0" + zlib.compress(b"\0" * size, 9))


def _itxt(size: int) -> bytes:
    return _chunk(b"iTXt", b"Comment\0\x01\0en\0Kommentar\0" + zlib.compress(b"\0" * size, 9))


@pytest.mark.parametrize("text", [_ztxt, _itxt], ids=["zTXt", "iTXt"])
def test_compressed_text_chunks_beyond_the_budget_are_refused(monkeypatch: pytest.MonkeyPatch, inflated,
                                                              text) -> None:  # type: ignore[no-untyped-def]
    pixels = _navtech_pixels()
    bomb = _png(pixels, extra_chunks=[text(MAX_PNG_TEXT_BYTES // 2)] * 40)  # 40 x 0.5 MiB: 20 MiB of text
    _no_libpng(monkeypatch)
    with pytest.raises(ScanFormatError, match=r"text chunks \(zTXt / iTXt\) inflate to more than 1 MiB"):
        decode_navtech_png_bytes(bomb)
    assert inflated.total <= png_image_data_size(pixels.shape[1], N_AZ, 8, 0, False) + MAX_PNG_TEXT_BYTES + 1


def test_small_text_chunks_are_accepted_and_decoded_by_libpng() -> None:
    pixels = _navtech_pixels()
    data = _png(pixels, extra_chunks=[_ztxt(100), _itxt(100), _chunk(b"tEXt", b"Software\0radar")])
    scan = decode_navtech_png_bytes(data)
    np.testing.assert_array_equal(scan.power, pixels[:, NAVTECH_META_COLUMNS:].astype(np.float32) / 255.0)


# ---- the plain path: the rows already inflated are decoded here, identically to libpng ------------------------

@pytest.mark.parametrize("filters", ["none", "sub", "up", "mixed-0-1-2"])
def test_plain_png_rows_decode_like_libpng_without_a_second_inflate(monkeypatch: pytest.MonkeyPatch,
                                                                   filters: str) -> None:
    pixels = _navtech_pixels(seed=3)
    rng = np.random.default_rng(1)
    kinds = {"none": [0] * N_AZ, "sub": [1] * N_AZ, "up": [2] * N_AZ,
             "mixed-0-1-2": list(rng.integers(0, 3, N_AZ))}[filters]
    data = _png(pixels, kinds, idat_split=5000)
    reference = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(reference, pixels)
    _no_libpng(monkeypatch)
    scan = decode_navtech_png_bytes(data)
    np.testing.assert_array_equal(scan.power, pixels[:, NAVTECH_META_COLUMNS:].astype(np.float32) / 255.0)
    np.testing.assert_array_equal(scan.timestamps_us, np.ascontiguousarray(pixels[:, :8]).view("<i8").ravel())


@pytest.mark.parametrize("kinds", [[3], [4], [0, 1, 2, 3, 4]], ids=["average", "paeth", "all-five"])
def test_average_and_paeth_rows_go_to_libpng(kinds: list[int]) -> None:
    pixels = _navtech_pixels(seed=4)
    data = _png(pixels, (kinds * N_AZ)[:N_AZ])
    scan = decode_navtech_png_bytes(data)
    np.testing.assert_array_equal(scan.power, pixels[:, NAVTECH_META_COLUMNS:].astype(np.float32) / 255.0)


def test_a_wrong_crc_is_left_to_libpng_which_refuses_it() -> None:
    data = bytearray(_png(_navtech_pixels()))
    end_of_first_idat = data.index(b"IDAT") + 4 + struct.unpack(">I", data[data.index(b"IDAT") - 4:
                                                                            data.index(b"IDAT")])[0]
    data[end_of_first_idat] ^= 0xFF  # the IDAT's CRC
    with pytest.raises(ScanFormatError, match="not a readable PNG image"):
        decode_navtech_png_bytes(bytes(data))


def test_opencv_written_and_real_scans_decode_as_before() -> None:
    """The shipped demo queries (OpenCV-written, Sub rows) and, where present, real Oxford scans (libpng with
    its mixed filters) decode to exactly OpenCV's pixels and metadata."""
    files = sorted(DEMO_QUERIES.glob("*.png"))[:3] + sorted(REAL_OXFORD.glob("*.png"))[:3]
    assert files
    for path in files:
        data = path.read_bytes()
        check_png_image_data(data)
        scan = decode_navtech_png_bytes(data)
        raw = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(scan.power, raw[:, NAVTECH_META_COLUMNS:].astype(np.float32) / 255.0)
        stamps = np.ascontiguousarray(raw[:, :8]).view("<i8").ravel()
        np.testing.assert_array_equal(scan.timestamps_us, stamps)
        assert scan.timestamp_us == int(path.stem)


# ---- 5. Navtech timestamps that are no time -------------------------------------------------------------------

def _with_stamps(stamps: np.ndarray) -> np.ndarray:
    raw = _navtech_pixels()
    raw[:, 0:8] = np.asarray(stamps, "<i8").view(np.uint8).reshape(N_AZ, 8)
    return raw


def _npy(raw: np.ndarray) -> bytes:
    import io
    buf = io.BytesIO()
    np.save(buf, raw)
    return buf.getvalue()


def _bytes_stamps(fill: int) -> np.ndarray:
    """Timestamps as the QA's edit made them: every byte 7 (top byte) set to ``fill``."""
    raw = _navtech_pixels()
    raw[:, 7] = fill
    return np.ascontiguousarray(raw[:, :8]).view("<i8").ravel()


@pytest.mark.parametrize(("stamps", "words"), [
    (_bytes_stamps(0x80), "is -92"),  # top byte 0x80: about -9.2e18
    (np.full(N_AZ, -1, np.int64), "is -1 us"),  # all bytes 0xFF
    (T0_US + np.arange(N_AZ) * 625 - T0_US - 1000, "is -1000 us"),
    (np.full(N_AZ, MAX_SCAN_TIMESTAMP_US + 1, np.int64), f"is {MAX_SCAN_TIMESTAMP_US + 1} us"),
], ids=["top-byte-0x80", "all-0xff", "first-rows-negative", "beyond-2^62"])
def test_timestamps_outside_the_epoch_range_are_refused(stamps: np.ndarray, words: str) -> None:
    raw = _with_stamps(stamps)
    for decode, data in ((decode_navtech_png_bytes, _png(raw)), (decode_navtech_npy_bytes, _npy(raw))):
        with pytest.raises(ScanFormatError, match="microseconds since the Unix epoch, 0..2\\^62") as err:
            decode(data)
        assert "timestamp of azimuth row 0" in str(err.value) and words in str(err.value)


def test_decreasing_and_too_long_sweeps_are_refused_with_the_rows() -> None:
    stamps = T0_US + np.arange(N_AZ, dtype=np.int64) * 625
    stamps[10] = stamps[9] - 1
    with pytest.raises(ScanFormatError, match=r"decrease from row 9 to row 10 \(.* -> .* us\)"):
        decode_navtech_png_bytes(_png(_with_stamps(stamps)))
    with pytest.raises(ScanFormatError, match=r"span 1\.26 s; one sweep takes at most 1 s"):
        decode_navtech_png_bytes(_png(_with_stamps(T0_US + np.arange(N_AZ, dtype=np.int64) * 20_000)))


def test_real_simulated_and_zero_based_timestamps_are_accepted() -> None:
    for start in (0, T0_US, MAX_SCAN_TIMESTAMP_US - 10**6):
        scan = RadarScan.from_power(np.zeros((N_AZ, N_BINS), np.uint8), "boreas", start)
        assert decode_navtech_png_bytes(encode_navtech_png_bytes(scan)).timestamp_us == start
    equal = _with_stamps(np.full(N_AZ, T0_US, np.int64))  # a sensor that stamps a whole sweep at once
    assert decode_navtech_npy_bytes(_npy(equal)).timestamp_us == T0_US


def test_a_scan_file_of_more_chunks_than_the_bound_is_refused_naming_the_file(tmp_path: Path) -> None:
    """``read_navtech_png`` (folders, ``reradar info``): the chunk bound's refusal names the file, not "upload"
    (QA, session 25)."""
    pixels = _navtech_pixels()
    stream_len = len(zlib.compress(_filtered(pixels, [0] * N_AZ), 9))
    path = tmp_path / "1000000.png"
    path.write_bytes(_png(pixels, idat_split=max(1, stream_len // MAX_PNG_CHUNKS)))
    with pytest.raises(ScanFormatError) as err:
        read_navtech_png(path)
    assert str(err.value).startswith(f"{path}: not a readable PNG image: more than 10,000 chunks")
    assert "upload" not in str(err.value)
