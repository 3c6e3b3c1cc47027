"""Navtech polar radar scans: the ``RadarScan`` dataclass and its PNG / .npy readers and writers.

Navtech PNG byte layout (Oxford Radar RobotCar, Boreas, MulRan, OORD all share it), one row per azimuth:

==========  =======  ===========================================================
columns     dtype    meaning
==========  =======  ===========================================================
0-7         int64    UTC timestamp of the azimuth, microseconds, little-endian
8-9         uint16   encoder value, little-endian; azimuth = encoder * pi / 2800 rad
10          uint8    valid flag (non-zero = valid)
11-         uint8    power per range bin, 0..255 (log-compressed by the sensor)
==========  =======  ===========================================================

The PNG is 8-bit single channel, so the metadata bytes are stored as pixel values.

Uploads are sized from their header before anything is decoded (``scan_header``): a PNG's IHDR chunk and an
.npy file's header state the image / array shape, so a 1 KB file that declares 60000 x 60000 pixels is refused
without allocating them. Lossy images (JPEG, WebP, ...) are not radar scans and are refused by name.
"""

from __future__ import annotations

import io
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np

from reradar_core.errors import ScanFormatError, ScanTooLargeError
from reradar_core.io.presets import ENCODER_TICKS_PER_TURN, PRESETS, RadarPreset, get_preset

__all__ = [
    "max_scan_file_bytes",
    "RadarScan",
    "NAVTECH_META_COLUMNS",
    "read_navtech_png",
    "write_navtech_png",
    "decode_navtech_png_bytes",
    "decode_navtech_npy_bytes",
    "NpyLayout",
    "encode_navtech_png_bytes",
    "read_polar_npy",
    "load_scan",
    "load_scan_bytes",
    "infer_preset",
    "ScanHeader",
    "sniff_scan_format",
    "read_png_header",
    "png_incomplete",
    "check_png_image_data",
    "png_image_data_size",
    "MAX_PNG_TEXT_BYTES",
    "MAX_PNG_CHUNKS",
    "read_npy_header",
    "scan_header",
    "LOSSY_FORMATS",
    "check_navtech_layout",
    "check_png_sides",
    "require_scan",
    "check_header_size",
    "check_polar_shape",
    "check_scan_sides",
    "has_navtech_metadata",
    "MIN_SCAN_SIDE",
    "MAX_SCAN_SIDE",
    "MAX_SCAN_TIMESTAMP_US",
    "navtech_png_first_time_us",
]

#: How far past [0, 1] a scan's power may reach (float rounding of value / 255).
_POWER_SLACK = 1e-4
#: Metadata columns in front of the range bins in a Navtech PNG row.
NAVTECH_META_COLUMNS = 11
_RAD_PER_TICK = 2.0 * np.pi / ENCODER_TICKS_PER_TURN


@dataclass
class RadarScan:
    """One polar radar sweep.

    Attributes:
        power: (A, R) float32 in [0, 1]; row a = azimuth a, column r = range bin r.
        azimuths: (A,) float64 radians in [0, 2*pi), clockwise from the sensor's +x (forward) axis.
        timestamps_us: (A,) int64 UTC microseconds at which each azimuth was measured.
        range_resolution_m: metres per range bin.
        range_offset_m: range of bin 0's centre, metres (``range = offset + bin * resolution``).
        valid: (A,) bool, False where the sensor flagged the azimuth invalid.
        preset: name of the radar preset the scan was read with, if known.
    """

    power: np.ndarray
    azimuths: np.ndarray
    timestamps_us: np.ndarray
    range_resolution_m: float
    range_offset_m: float = 0.0
    valid: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    preset: str | None = None

    def __post_init__(self) -> None:
        self.power = np.asarray(self.power, dtype=np.float32)
        if self.power.ndim != 2 or self.power.shape[0] < 2 or self.power.shape[1] < 2:
            raise ScanFormatError(
                f"scan power must be a 2-D (azimuths x range bins) array, got shape {self.power.shape}"
            )
        # min / max propagate NaN, so one pass each checks finiteness and the [0, 1] scale together
        lo, hi = float(self.power.min()), float(self.power.max())
        if not (np.isfinite(lo) and np.isfinite(hi)):
            raise ScanFormatError("scan power contains NaN or infinite values")
        if lo < -_POWER_SLACK or hi > 1.0 + _POWER_SLACK:
            hint = (" (8-bit values? divide by 255, or build it with RadarScan.from_power, which scales integer "
                    "0-255 arrays)"
                    if hi <= 255.0 + _POWER_SLACK and lo >= -_POWER_SLACK else "")
            raise ScanFormatError(f"scan power must be in [0, 1] (the Navtech 8-bit value / 255), got values in "
                                  f"[{lo:.4g}, {hi:.4g}]{hint}")
        n_az = self.power.shape[0]
        self.azimuths = np.asarray(self.azimuths, dtype=np.float64)
        self.timestamps_us = np.asarray(self.timestamps_us, dtype=np.int64)
        if self.valid.size == 0:
            self.valid = np.ones(n_az, dtype=bool)
        self.valid = np.asarray(self.valid, dtype=bool)
        for name in ("azimuths", "timestamps_us", "valid"):
            arr = getattr(self, name)
            if arr.shape != (n_az,):
                raise ScanFormatError(f"scan {name} must have shape ({n_az},), got {arr.shape}")
        if not np.all(np.isfinite(self.azimuths)):
            raise ScanFormatError("scan azimuths contain NaN or infinite values")
        az_max = float(np.max(np.abs(self.azimuths)))
        if az_max > 2.0 * np.pi + 1e-6:
            hint = "; they look like degrees: pass numpy.radians(azimuths)" if az_max <= 360.0 + 1e-6 else ""
            raise ScanFormatError(f"scan azimuths must be radians in [0, 2*pi), got values up to {az_max:.4g}{hint}")
        if not (self.range_resolution_m > 0 and np.isfinite(self.range_resolution_m)):
            raise ScanFormatError(f"range resolution must be positive, got {self.range_resolution_m}")
        if not np.isfinite(self.range_offset_m):
            raise ScanFormatError(f"range offset must be a finite number of metres, got {self.range_offset_m}")

    @property
    def num_azimuths(self) -> int:
        return int(self.power.shape[0])

    @property
    def num_range_bins(self) -> int:
        return int(self.power.shape[1])

    @property
    def ranges_m(self) -> np.ndarray:
        """(R,) float64 range of each bin centre, metres."""
        return self.range_offset_m + np.arange(self.num_range_bins) * self.range_resolution_m

    @property
    def timestamp_us(self) -> int:
        """Scan timestamp: the first azimuth's time, microseconds (Oxford names its PNG files so)."""
        return int(self.timestamps_us[0])

    def with_power(self, power: np.ndarray) -> RadarScan:
        """A copy with another power array (same metadata)."""
        return replace(self, power=power)

    @classmethod
    def from_power(
        cls,
        power: np.ndarray,
        preset: str | RadarPreset = "oxford",
        start_time_us: int = 0,
    ) -> RadarScan:
        """Build a scan from a bare (A, R) power array with uniform azimuths and the preset's geometry: floats in
        [0, 1], or integer 8-bit values (0-255, scaled by 1/255). A (R, A) array of the preset's R is refused as
        transposed."""
        p = get_preset(preset)
        power = np.asarray(power)
        if power.ndim != 2:
            raise ScanFormatError(f"polar array must be 2-D (azimuths x range bins), got shape {power.shape}")
        if power.shape[0] > power.shape[1] and power.shape[0] == p.num_range_bins:
            raise ScanFormatError(f"polar array of shape {power.shape} looks transposed: preset {p.name!r} has "
                                  f"{p.num_range_bins} range bins, so pass it as (azimuths, range bins) (array.T)")
        n_az = power.shape[0]
        if power.dtype.kind in "iu":  # 8-bit values in any integer type
            if power.size and (int(power.min()) < 0 or int(power.max()) > 255):
                raise ScanFormatError(f"integer polar values must be 8-bit (0-255), got [{int(power.min())}, "
                                      f"{int(power.max())}]; give floats in [0, 1] for other scales")
            power = power.astype(np.float32) / 255.0
        azimuths = np.arange(n_az) * (2.0 * np.pi / n_az)
        dt_us = int(round(p.sweep_period_s * 1e6 / n_az))
        timestamps = start_time_us + np.arange(n_az, dtype=np.int64) * dt_us
        return cls(power, azimuths, timestamps, p.range_resolution_m, p.range_offset_m, preset=p.name)


def require_scan(scan: object, what: str) -> RadarScan:
    """``scan`` itself when it is a ``RadarScan``, else ``ConfigError`` naming ``what`` and how to make one (an image
    array, a path or None would otherwise fail deep inside with an AttributeError)."""
    if not isinstance(scan, RadarScan):
        from reradar_core.errors import ConfigError

        raise ConfigError(f"{what} takes a RadarScan (reradar_core.io.scan.load_scan(path, preset), or "
                          f"RadarScan.from_power(polar_array, preset)), got {type(scan).__name__}")
    return scan


def presets_with_bins(num_range_bins: int) -> list[RadarPreset]:
    """The radar presets whose scans have ``num_range_bins`` range bins (3,360: boreas, boreas-2021, mulran)."""
    return [p for p in PRESETS.values() if p.num_range_bins == num_range_bins]


def preset_bin_sizes(presets: list[RadarPreset]) -> str:
    """``boreas 0.0596 m/bin, boreas-2021 0.04381 m/bin``: what messages on an ambiguous preset name."""
    return ", ".join(f"{p.name} {p.range_resolution_m} m/bin" for p in presets)


def infer_preset(num_range_bins: int, source: str = "scan") -> RadarPreset:
    """The preset of a scan with ``num_range_bins`` range bins, when the count names one range geometry: 3,768 ->
    oxford (OORD has the same geometry). 3,360 bins fit boreas, boreas-2021 and mulran, whose bins differ in size
    and offset: that count is ambiguous and refused, as is a count no preset has.

    Raises:
        ScanFormatError: no preset, or presets of different geometry, have that bin count; the message asks
            for the preset (``--preset``).
    """
    fits = presets_with_bins(num_range_bins)
    if fits and all(_same_geometry(p, fits[0]) for p in fits):
        return fits[0]
    if fits:
        raise ScanFormatError(
            f"{source}: {num_range_bins} range bins fit several radar presets with different range geometry "
            f"({preset_bin_sizes(fits)}); pass the preset the scan "
            "was recorded with (--preset; preset= in Python)")
    raise ScanFormatError(
        f"{source}: cannot infer the radar preset from {num_range_bins} range bins{_navtech_hint(num_range_bins)}; "
        "pass the preset explicitly "
        f"(known: {sorted(PRESETS)}), or convert scans of another layout or resolution with "
        f"`reradar import-scans`"
    )


def range_bins_ambiguous(num_range_bins: int) -> bool:
    """True when radar presets of different range geometry have ``num_range_bins`` bins (3,360: boreas,
    boreas-2021 and mulran), so the count alone does not say how long a bin is."""
    fits = presets_with_bins(num_range_bins)
    return any(not _same_geometry(p, fits[0]) for p in fits[1:])


def same_range_geometry(a: str | RadarPreset, b: str | RadarPreset) -> bool:
    """True when presets ``a`` and ``b`` (names or presets) describe scans alike (bins, bin size, offset, sweep)."""
    return _same_geometry(get_preset(a), get_preset(b))


def _same_geometry(a: RadarPreset, b: RadarPreset) -> bool:
    return (a.range_resolution_m, a.range_offset_m, a.num_range_bins, a.num_azimuths, a.sweep_period_s,
            a.landmark_min_range_bins) == (b.range_resolution_m, b.range_offset_m, b.num_range_bins,
                                           b.num_azimuths, b.sweep_period_s, b.landmark_min_range_bins)


def _upload_preset(num_range_bins: int, map_preset: str | RadarPreset | None = None) -> RadarPreset:
    """The preset the service gives an uploaded Navtech scan sent without one: the target map's preset
    (``map_preset``) when it has that bin count, else the first preset with that bin count (boreas for 3,360
    bins, although mulran and boreas-2021 have as many). Kept for the HTTP API, whose requests may omit
    ``preset``; files read here use ``infer_preset``, which refuses the ambiguous counts."""
    fits = [p for p in PRESETS.values() if p.num_range_bins == num_range_bins]
    wanted = get_preset(map_preset) if map_preset is not None else None
    if wanted is not None and wanted in fits:
        return wanted
    return fits[0] if fits else infer_preset(num_range_bins, "upload")


#: Accepted polar scan sizes (azimuths and range bins): anything smaller is not a radar sweep; larger ones
#: would make one request monopolise the CPU.
MIN_SCAN_SIDE = 64
MAX_SCAN_SIDE = 8192


def check_scan_sides(num_azimuths: int, num_range_bins: int, source: str = "scan") -> None:
    """Refuse a polar array with fewer than ``MIN_SCAN_SIDE`` or more than ``MAX_SCAN_SIDE`` azimuths or range
    bins (not a full sweep, or a memory bomb), whatever its preset.

    Raises:
        ScanFormatError: the shape found and the one expected.
    """
    a, r = int(num_azimuths), int(num_range_bins)
    if not (MIN_SCAN_SIDE <= a <= MAX_SCAN_SIDE and MIN_SCAN_SIDE <= r <= MAX_SCAN_SIDE):
        raise ScanFormatError(
            f"{source}: {a} azimuths x {r} range bins; expected a full sweep with {MIN_SCAN_SIDE}.."
            f"{MAX_SCAN_SIDE} of each (e.g. 400 x 3360 Boreas, 400 x 3768 Oxford)")


#: Metadata columns in front of the range bins of a Navtech image (timestamp 8, encoder 2, valid flag 1).
NAVTECH_METADATA_COLUMNS = 11


def _navtech_hint(num_range_bins: int) -> str:
    """A hint when a 'polar' array has exactly a Navtech image's width (metadata columns + a preset's bins)."""
    bins = num_range_bins - NAVTECH_METADATA_COLUMNS
    if any(p.num_range_bins == bins for p in PRESETS.values()):
        return (f" ({num_range_bins} = {NAVTECH_METADATA_COLUMNS} metadata columns + {bins} range bins: a Navtech "
                "image? send it with scan_layout=navtech, --scan-layout navtech on the command line)")
    return ""


def check_polar_shape(num_azimuths: int, num_range_bins: int, preset: RadarPreset, source: str = "scan") -> None:
    """Refuse a polar (azimuths x range bins) array whose layout contradicts ``preset``: a side outside
    ``MIN_SCAN_SIDE..MAX_SCAN_SIDE``, more azimuth rows than range bins (a transposed array), or more range bins
    than the preset has (a scan cropped in range is accepted).

    Raises:
        ScanFormatError: what is wrong and what to do.
    """
    a, r = int(num_azimuths), int(num_range_bins)
    check_scan_sides(a, r, source)
    if a > r:
        raise ScanFormatError(
            f"{source}: scan has {a} rows (azimuths) x {r} columns (range bins): more azimuths than range bins, "
            "so the array looks transposed; a polar array is (azimuths, range bins), e.g. 400 x 3360; "
            "convert it with `reradar import-scans --transposed`")
    if r > preset.num_range_bins:
        raise ScanFormatError(
            f"{source}: {r} range bins, but preset {preset.name!r} has {preset.num_range_bins} bins of "
            f"{preset.range_resolution_m} m{_navtech_hint(r)}; pass the preset this scan was recorded with, or "
            "convert scans of another layout or resolution with `reradar import-scans`")


# ---- headers: sizes before decoding --------------------------------------------------------------------------

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_NPY_MAGIC = b"\x93NUMPY"

#: Image formats recognised by their magic bytes that are refused as scans: lossy ones (their compression
#: artefacts would be read as radar returns) and GIF (palette-quantised, and no radar writes it).
LOSSY_FORMATS = ("jpeg", "jpeg2000", "webp", "gif", "heif/avif")


def why_format_refused(kind: str) -> str:
    """Why an image format of ``LOSSY_FORMATS`` is not a scan, for a message."""
    return "palette-quantised" if kind == "gif" else "lossy"


_MAGIC: tuple[tuple[bytes, int, str], ...] = (
    (PNG_SIGNATURE, 0, "png"),
    (_NPY_MAGIC, 0, "npy"),
    (b"\xff\xd8\xff", 0, "jpeg"),
    (b"\x00\x00\x00\x0cjP  ", 0, "jpeg2000"),
    (b"\xff\x4f\xff\x51", 0, "jpeg2000"),
    (b"WEBP", 8, "webp"),
    (b"GIF8", 0, "gif"),
    (b"ftypheic", 4, "heif/avif"),
    (b"ftypavif", 4, "heif/avif"),
    (b"ftypmif1", 4, "heif/avif"),
    (b"BM", 0, "bmp"),
    (b"II*\x00", 0, "tiff"),
    (b"MM\x00*", 0, "tiff"),
)


@dataclass(frozen=True)
class ScanHeader:
    """What a scan file's header declares, read without decoding it.

    Attributes:
        format: ``png`` or ``npy``.
        shape: (rows, columns) of the image / array (PNG rows = azimuths, columns = 11 metadata + range bins).
        itemsize: bytes per decoded element (1 for 8-bit PNG, the dtype's size for .npy).
        dtype: numpy dtype string of the decoded array (``|u1`` for PNG).
    """

    format: str
    shape: tuple[int, int]
    itemsize: int
    dtype: str

    @property
    def num_pixels(self) -> int:
        return self.shape[0] * self.shape[1]

    @property
    def decoded_bytes(self) -> int:
        """Bytes the decoded image / array takes in memory."""
        return self.num_pixels * self.itemsize


def sniff_scan_format(data: bytes) -> str:
    """The file format named by ``data``'s magic bytes: ``png``, ``npy``, one of ``LOSSY_FORMATS``, ``bmp``,
    ``tiff`` or ``unknown``."""
    for magic, offset, name in _MAGIC:
        if data[offset:offset + len(magic)] == magic:
            return name
    return "unknown"


def read_png_header(data: bytes) -> ScanHeader:
    """Shape and bit depth from a PNG's IHDR chunk (the first 33 bytes); refuses anything but an 8-bit
    single-channel (greyscale) PNG, the Navtech layout.

    Raises:
        ScanFormatError: not a PNG, truncated header, zero or non-greyscale / non-8-bit image.
    """
    if data[:8] != PNG_SIGNATURE:
        raise ScanFormatError("upload is not a PNG image (no PNG signature)")
    if len(data) < 33 or data[12:16] != b"IHDR":
        raise ScanFormatError("upload is not a readable PNG image (corrupt or truncated header)")
    length, = struct.unpack(">I", data[8:12])
    width, height, bit_depth, color_type = struct.unpack(">IIBB", data[16:26])
    if length != 13 or width == 0 or height == 0:
        raise ScanFormatError("upload is not a readable PNG image (corrupt or truncated header)")
    if bit_depth != 8 or color_type != 0:
        kinds = {0: "greyscale", 2: "colour", 3: "palette", 4: "greyscale+alpha", 6: "colour+alpha"}
        raise ScanFormatError(
            f"a Navtech PNG must be 8-bit single-channel (greyscale); this one is {bit_depth}-bit "
            f"{kinds.get(color_type, f'colour type {color_type}')}"
        )
    return ScanHeader("png", (int(height), int(width)), 1, "|u1")


def read_npy_header(data: bytes, size: int | None = None) -> ScanHeader:
    """Shape and dtype from an .npy file's header (numpy's own parser; the header is at most 10 kB).

    ``data`` may be just the file's beginning; ``size`` is then the whole file's length in bytes.

    Raises:
        ScanFormatError: not an .npy file, not a 2-D numeric array, Fortran order, or more or fewer data bytes
        than the header declares.
    """
    from numpy.lib import format as npy_format

    if data[:6] != _NPY_MAGIC:
        raise ScanFormatError("upload is not a readable .npy array (no .npy magic)")
    fp = io.BytesIO(data)
    try:
        version = npy_format.read_magic(fp)
    except (ValueError, EOFError, struct.error):
        raise ScanFormatError("upload is not a readable .npy array (malformed .npy header)") from None
    if version not in ((1, 0), (2, 0), (3, 0)):
        raise ScanFormatError(f"upload is not a readable .npy array (unsupported .npy format version "
                              f"{version[0]}.{version[1]}; numpy writes 1.0, 2.0 or 3.0)")
    try:
        if version == (1, 0):
            shape, fortran, dtype = npy_format.read_array_header_1_0(fp)
        else:
            shape, fortran, dtype = npy_format.read_array_header_2_0(fp)
    except (ValueError, SyntaxError, TypeError, EOFError, struct.error) as exc:
        # numpy's messages show parser internals (an AST node's address) or byte counts of the part it was given
        short = isinstance(exc, EOFError) or str(exc).startswith("EOF")
        what = "truncated or oversized .npy header" if short else "malformed .npy header"
        raise ScanFormatError(f"upload is not a readable .npy array ({what})") from None
    if len(shape) != 2:
        raise ScanFormatError(f"polar array must be 2-D (azimuths x range bins), got shape {tuple(shape)}")
    if dtype.kind not in "uif" or dtype.hasobject:
        raise ScanFormatError(f"polar array must be numeric, got dtype {dtype}")
    if fortran:
        raise ScanFormatError("polar array must be C-ordered (np.save of a regular array), not Fortran-ordered")
    rows, cols = int(shape[0]), int(shape[1])
    declared, held = rows * cols * dtype.itemsize, (len(data) if size is None else size) - fp.tell()
    if declared > held:
        raise ScanFormatError(f"upload is not a readable .npy array (header declares {rows} x {cols} "
                              f"{dtype} but the file is shorter: truncated?)")
    if declared < held:  # np.save writes nothing after the data: two files joined, or a header that lies
        raise ScanFormatError(f"upload is not a readable .npy array (header declares {rows} x {cols} {dtype}, "
                              f"{declared:,} bytes of data, but {held - declared:,} more "
                              f"{'bytes follow' if held - declared > 1 else 'byte follows'} them; send "
                              "the file np.save wrote, unchanged)")
    return ScanHeader("npy", (rows, cols), int(dtype.itemsize), dtype.str)


def max_scan_file_bytes(max_pixels: int) -> int:
    """The largest file a scan within ``max_pixels`` can be: a float64 .npy of that many pixels plus the Navtech
    metadata columns of ``MAX_SCAN_SIDE`` azimuths and 64 KiB of header (an 8-bit PNG, even incompressible, is
    smaller). A larger file holds something besides the scan (QA session 40: a PNG with 1.5 GB after its end
    marker was read whole into memory by a map build)."""
    return 8 * (int(max_pixels) + NAVTECH_META_COLUMNS * MAX_SCAN_SIDE) + 65536


def check_header_size(header: ScanHeader, max_pixels: int, scan_layout: str = "polar") -> tuple[int, int]:
    """The polar (azimuths, range bins) a scan header declares, after the size checks every scan input shares
    (uploads, archive scans of a map build): at most ``MAX_SCAN_SIDE`` of each and ``max_pixels`` pixels, at
    least ``MIN_SCAN_SIDE`` of each. A PNG, or an .npy with ``scan_layout="navtech"``, holds the
    ``NAVTECH_META_COLUMNS`` metadata columns before the range bins.

    Raises:
        ScanTooLargeError: too many pixels, azimuths or range bins. ScanFormatError: too few.
    """
    rows, cols = header.shape
    navtech = header.format == "png" or scan_layout == "navtech"
    bins = cols - NAVTECH_META_COLUMNS if navtech else cols
    if rows > MAX_SCAN_SIDE or bins > MAX_SCAN_SIDE or header.num_pixels > max_pixels:
        raise ScanTooLargeError(
            f"scan declares {rows} azimuths x {bins} range bins ({header.num_pixels:,} pixels); accepted are up "
            f"to {MAX_SCAN_SIDE} of each and {max_pixels:,} pixels (a Navtech sweep is 400 x 3,360-3,768)")
    if rows < MIN_SCAN_SIDE or bins < MIN_SCAN_SIDE:
        layout = (f" ({cols} columns, the first {NAVTECH_META_COLUMNS} of which are Navtech metadata)"
                  if navtech else "")
        raise ScanFormatError(
            f"scan has {rows} azimuths x {max(bins, 0)} range bins{layout}; expected a full sweep with "
            f"{MIN_SCAN_SIDE}..{MAX_SCAN_SIDE} of each (e.g. 400 x 3360 Boreas, 400 x 3768 Oxford)")
    return rows, bins


def scan_header(data: bytes, size: int | None = None) -> ScanHeader:
    """The header of an uploaded scan (PNG or .npy, told apart by content, not by file name).

    ``data`` may be just the file's first bytes (64 kB hold any header); ``size`` is then the file's length.

    Raises:
        ScanFormatError: a lossy image (JPEG, WebP, ...), another format, or a bad PNG / .npy header.
    """
    kind = sniff_scan_format(data)
    if kind == "png":
        return read_png_header(data)
    if kind == "npy":
        return read_npy_header(data, size)
    if kind in LOSSY_FORMATS:
        raise ScanFormatError(f"{kind.upper()} images are {why_format_refused(kind)} and are not accepted as radar "
                              "scans: send the radar's lossless Navtech PNG or an (A, R) .npy array")
    what = "empty file" if not data and not size else (kind.upper() if kind != "unknown" else "unrecognised format")
    raise ScanFormatError(f"upload is not a Navtech PNG or .npy array ({what})")


def _scan_from_raw(raw: np.ndarray, preset: str | RadarPreset | None, source: str,
                   pick_preset: Callable[[int], RadarPreset] | None = None) -> RadarScan:
    """A Navtech PNG's pixels (uint8 (A, 11 + R)) as a scan; without ``preset`` the range-bin count picks one
    (``pick_preset``; default ``infer_preset``, which refuses an ambiguous count)."""
    if raw.ndim != 2 or raw.dtype != np.uint8:
        raise ScanFormatError(
            f"{source}: a Navtech PNG must be 8-bit single-channel, got dtype {raw.dtype} shape {raw.shape}"
        )
    if raw.shape[1] <= NAVTECH_META_COLUMNS + 1 or raw.shape[0] < 2:
        raise ScanFormatError(
            f"{source}: a Navtech PNG needs >= 2 rows and more than {NAVTECH_META_COLUMNS} columns "
            f"(11 metadata + range bins), got shape {raw.shape}"
        )
    num_bins = raw.shape[1] - NAVTECH_META_COLUMNS
    if raw.shape[0] > num_bins and presets_with_bins(raw.shape[0] - NAVTECH_META_COLUMNS):
        # its rows are a preset's columns: said before anything else ("cannot infer the preset from 389 bins")
        raise ScanFormatError(
            f"{source}: image has {raw.shape[0]} rows x {raw.shape[1]} columns: more azimuth rows than range bins, "
            f"so it looks transposed; a Navtech PNG is (azimuths, {NAVTECH_META_COLUMNS} metadata columns + range "
            f"bins), e.g. 400 x {3360 + NAVTECH_META_COLUMNS}: save it untransposed (polar data without Navtech "
            "metadata: `reradar import-scans --transposed`)")
    meta = np.ascontiguousarray(raw[:, :NAVTECH_META_COLUMNS])
    timestamps = meta[:, 0:8].copy().view("<i8").reshape(-1)
    encoder = meta[:, 8:10].copy().view("<u2").reshape(-1)
    valid = meta[:, 10] != 0
    if preset is not None:
        p = get_preset(preset)
    else:
        p = pick_preset(num_bins) if pick_preset is not None else infer_preset(num_bins, source)
    check_navtech_layout(encoder, timestamps, valid, num_bins, p, source)
    fft = raw[:, NAVTECH_META_COLUMNS:].astype(np.float32) / 255.0
    azimuths = (encoder.astype(np.float64) * _RAD_PER_TICK) % (2.0 * np.pi)
    return RadarScan(fft, azimuths, timestamps, p.range_resolution_m, p.range_offset_m, valid, preset=p.name)


#: A row's encoder step may differ from the nominal 2*pi/A by this fraction (real Navtech scans: < 1 %).
_ENCODER_STEP_TOLERANCE = 0.5
#: Fraction of valid rows whose encoder step must be nominal (dropped azimuths leave a few double steps).
_MIN_NOMINAL_STEP_FRACTION = 0.8
#: Longest plausible sweep, seconds (Navtech sensors turn at 4 Hz; a 4x margin).
_MAX_SWEEP_S = 1.0
#: Largest azimuth timestamp accepted, microseconds since the Unix epoch (2**62, year ~148,000): far beyond any
#: real time, and small enough that int64 arithmetic on timestamps (mid-sweep offsets, spans) cannot overflow.
#: Scan archives name their files within the same bound (``service.core.archive``).
MAX_SCAN_TIMESTAMP_US = 2**62


def check_navtech_layout(encoder: np.ndarray, timestamps_us: np.ndarray, valid: np.ndarray, num_range_bins: int,
                         preset: RadarPreset, source: str = "scan", strict_bins: bool = False) -> None:
    """Refuse a Navtech PNG whose geometry or metadata contradict its preset.

    A scan of another layout (no metadata columns, transposed, other range-bin count) decodes into garbage
    azimuths and ranges without any error and then localizes confidently at a wrong pose, so the reader checks:
    the scan has no more range bins than the preset (exactly as many with ``strict_bins``; a scan cropped in
    range is accepted by default); the encoder column advances by about ``5600 / A`` ticks per row
    (azimuths evenly spaced around one turn); the azimuth timestamps do not decrease and span at most one
    second. Rows flagged invalid are ignored, except that every row's timestamp must lie in
    0..``MAX_SCAN_TIMESTAMP_US`` (a negative one, e.g. top byte 0x80 or all 0xFF, is no time).

    Args:
        encoder: (A,) uint16 encoder ticks (columns 8-9). timestamps_us: (A,) int64 (columns 0-7).
        valid: (A,) bool (column 10). num_range_bins: range-bin columns. preset: the scan's preset.
        source: file name or "upload", used in messages.
        strict_bins: require exactly the preset's range-bin count.

    Raises:
        ScanFormatError: with what is wrong and what to do (``reradar import-scans`` for foreign layouts).
    """
    hint = ("scans of another layout or resolution can be converted with `reradar import-scans` "
            "(docs/CONVENTIONS.md, 'Importing scans')")
    if num_range_bins > preset.num_range_bins or (strict_bins and num_range_bins != preset.num_range_bins):
        raise ScanFormatError(
            f"{source}: {num_range_bins} range bins, but preset {preset.name!r} has {preset.num_range_bins} "
            f"bins of {preset.range_resolution_m} m; pass the preset this scan was recorded with, or {hint}")
    _check_navtech_metadata(encoder, timestamps_us, valid, source, hint)


def has_navtech_metadata(raw: np.ndarray) -> bool:
    """True when the 2-D uint8 image ``raw`` already is a Navtech scan: its first ``NAVTECH_META_COLUMNS`` columns
    hold a sweep's timestamps, encoder values and valid flags (``check_navtech_layout``'s metadata checks)."""
    if raw.ndim != 2 or raw.dtype != np.uint8 or raw.shape[0] < 2 or raw.shape[1] <= NAVTECH_META_COLUMNS + 1:
        return False
    meta = np.ascontiguousarray(raw[:, :NAVTECH_META_COLUMNS])
    try:
        _check_navtech_metadata(meta[:, 8:10].copy().view("<u2").reshape(-1), meta[:, 0:8].copy().view("<i8").reshape(-1),
                                meta[:, 10] != 0, "image", "")
    except ScanFormatError:
        return False
    return True


def _check_navtech_metadata(encoder: np.ndarray, timestamps_us: np.ndarray, valid: np.ndarray, source: str,
                            hint: str) -> None:
    rows = np.flatnonzero(np.asarray(valid, dtype=bool))
    if len(rows) < 2:
        raise ScanFormatError(f"{source}: fewer than 2 azimuth rows are flagged valid (column 10); {hint}")
    nominal = ENCODER_TICKS_PER_TURN / len(encoder)
    ticks = encoder[rows].astype(np.int64)
    step = np.diff(ticks) % ENCODER_TICKS_PER_TURN / np.diff(rows)
    nominal_rows = np.abs(step - nominal) <= _ENCODER_STEP_TOLERANCE * nominal
    if nominal_rows.mean() < _MIN_NOMINAL_STEP_FRACTION:
        raise ScanFormatError(
            f"{source}: the encoder column (8-9) does not advance by ~{nominal:.0f} ticks per azimuth row as a "
            f"Navtech sweep of {len(encoder)} azimuths does (only {nominal_rows.mean():.0%} of rows do): the image "
            f"has no Navtech metadata columns or is transposed; {hint}")
    stamps = np.asarray(timestamps_us, dtype=np.int64)
    # every row, flagged valid or not: the scan's timestamp is its first row's (RadarScan.timestamp_us), and
    # int64 arithmetic on them (mid-sweep times) must not overflow; a negative one is a corrupt or foreign column
    outside = np.flatnonzero((stamps < 0) | (stamps > MAX_SCAN_TIMESTAMP_US))
    if len(outside):
        r = int(outside[0])
        raise ScanFormatError(
            f"{source}: the timestamp of azimuth row {r} (columns 0-7, little-endian int64) is {int(stamps[r])} us; "
            f"Navtech timestamps are microseconds since the Unix epoch, 0..2^62 ({len(outside)} of "
            f"{len(stamps)} rows are outside that); {hint}")
    t = stamps[rows]
    back = np.flatnonzero(np.diff(t) < 0)
    if len(back):
        a, b = int(rows[back[0]]), int(rows[back[0] + 1])
        raise ScanFormatError(
            f"{source}: the azimuth timestamps (columns 0-7) decrease from row {a} to row {b} ({int(stamps[a])} -> "
            f"{int(stamps[b])} us); a sweep's azimuths are measured in increasing time; {hint}")
    span_s = (int(t[-1]) - int(t[0])) / 1e6
    if span_s > _MAX_SWEEP_S:
        raise ScanFormatError(
            f"{source}: the azimuth timestamps (columns 0-7) span {span_s:.3g} s; one sweep takes at most "
            f"{_MAX_SWEEP_S:.0f} s (a Navtech sensor turns at 4 Hz); {hint}")


#: Compressed image data read at most to find a PNG's first row (``navtech_png_first_time_us``): the 9 bytes it
#: needs come from the first few hundred bytes of a deflate stream; this bounds a malformed file.
_MAX_FIRST_ROW_IDAT_BYTES = 1 << 20
#: Chunks walked at most before the image data (a Navtech PNG has IHDR, maybe a few ancillary chunks, then IDAT).
_MAX_CHUNKS_BEFORE_IDAT = 256


def navtech_png_first_time_us(path: str | Path) -> int | None:
    """The first azimuth row's timestamp of a Navtech PNG file (columns 0-7, little-endian int64 microseconds:
    ``RadarScan.timestamp_us``), read without decoding the image.

    Only the chunks up to the image data are walked and only the first 9 bytes of its zlib stream (row 0's filter
    byte and its first 8 pixels) are inflated: a few small reads per file, where decoding a 400 x 3779 scan takes
    ~10 ms. Row 0 has no row above it, so PNG's filters reduce to "as is" (None, Up), "add the left byte" (Sub,
    Paeth) and "add half of it" (Average).

    Returns:
        The time in microseconds; None when the file is not an 8-bit greyscale, non-interlaced PNG whose first
        row can be read so, or that row holds no time (outside 0..``MAX_SCAN_TIMESTAMP_US``): a full decode
        (``read_navtech_png``) then says what is wrong with it.
    """
    try:
        with Path(path).open("rb") as fh:
            if fh.read(8) != PNG_SIGNATURE:
                return None
            head = fh.read(8 + 13 + 4)  # IHDR: length, type, 13 bytes, CRC
            if len(head) < 25 or head[4:8] != b"IHDR" or int.from_bytes(head[:4], "big") != 13:
                return None
            width, _height, depth, colour, _method, _filter, interlace = struct.unpack(">IIBBBBB", head[8:21])
            if depth != 8 or colour != 0 or interlace != 0 or width < 8:
                return None
            inflate = zlib.decompressobj()
            row = b""
            read = 0
            for _ in range(_MAX_CHUNKS_BEFORE_IDAT):
                chunk = fh.read(8)
                if len(chunk) < 8 or chunk[4:8] == b"IEND":
                    return None
                length = int.from_bytes(chunk[:4], "big")
                if chunk[4:8] != b"IDAT":
                    fh.seek(length + 4, 1)  # the chunk's body and CRC
                    continue
                left = length
                while left and len(row) < 9:
                    body = fh.read(min(left, 1 << 14))
                    if not body or read >= _MAX_FIRST_ROW_IDAT_BYTES:
                        return None  # a truncated file, or image data that yields nothing
                    read += len(body)
                    left -= len(body)
                    row += inflate.decompress(inflate.unconsumed_tail + body, 9 - len(row))
                if len(row) == 9:
                    break
                fh.seek(left + 4, 1)
            else:
                return None
    except (OSError, zlib.error):
        return None
    kind, raw = row[0], bytearray(row[1:9])
    if kind > 4:
        return None
    if kind in (1, 3, 4):  # Sub and Paeth add the left byte, Average half of it (the row above is zeros)
        for i in range(1, 8):
            raw[i] = (raw[i] + (raw[i - 1] if kind != 3 else raw[i - 1] // 2)) & 0xFF
    t = int.from_bytes(raw, "little", signed=True)
    return t if 0 <= t <= MAX_SCAN_TIMESTAMP_US else None


def _raw_from_scan(scan: RadarScan) -> np.ndarray:
    n_az = scan.num_azimuths
    raw = np.zeros((n_az, NAVTECH_META_COLUMNS + scan.num_range_bins), dtype=np.uint8)
    raw[:, 0:8] = scan.timestamps_us.astype("<i8").view(np.uint8).reshape(n_az, 8)
    encoder = np.round(np.mod(scan.azimuths, 2 * np.pi) / _RAD_PER_TICK).astype(np.int64) % ENCODER_TICKS_PER_TURN
    raw[:, 8:10] = encoder.astype("<u2").view(np.uint8).reshape(n_az, 2)
    raw[:, 10] = np.where(scan.valid, 255, 0).astype(np.uint8)
    raw[:, NAVTECH_META_COLUMNS:] = np.clip(np.round(scan.power * 255.0), 0, 255).astype(np.uint8)
    return raw


def png_incomplete(data: bytes, chunks: list[tuple[bytes, int, int]] | None = None) -> bool:
    """True when ``data`` (a PNG file's bytes) ends before its ``IEND`` chunk: truncated or cut mid-chunk.

    Checked before decoding so that libpng never sees a truncated file: it prints its own error line on stderr
    (outside our logging) before OpenCV returns nothing. ``chunks``: the file's ``_png_chunks`` when the caller
    walked them already (a walk of the chunk lengths, O(number of chunks); a chunk that overruns the file is
    the last one listed)."""
    chunks = _png_chunks(data) if chunks is None else chunks
    return not chunks or chunks[-1][0] != b"IEND" or chunks[-1][2] + 4 > len(data)  # + 4: IEND's CRC


def check_png_file(data: bytes, name: str) -> None:
    """Refuse the PNG file ``data`` (named ``name`` in messages) that libpng would fail on - truncated, or a chunk
    whose CRC does not match - before it is decoded, so that libpng never prints its own error line on stderr.

    Raises:
        ScanFormatError: not a PNG, truncated, a corrupt chunk, or more than ``MAX_PNG_CHUNKS`` chunks.
    """
    try:
        chunks = _png_chunks(data) if data[:8] == PNG_SIGNATURE else []
    except ScanFormatError as exc:  # the chunk walk's bound (MAX_PNG_CHUNKS) speaks of an upload: name the file
        raise ScanFormatError(f"{name}: {str(exc).removeprefix('upload is ')}") from None
    if png_incomplete(data, chunks):
        raise ScanFormatError(f"{name}: not a readable PNG image (corrupt or truncated)")
    bad_chunk = png_crc_mismatch(data, chunks)
    if bad_chunk is not None:
        raise ScanFormatError(f"{name}: not a readable PNG image (corrupt: its {bad_chunk} chunk fails its checksum)")


def png_crc_mismatch(data: bytes, chunks: list[tuple[bytes, int, int]] | None = None) -> str | None:
    """The type of the first chunk of ``data`` (a complete PNG file's bytes: ``png_incomplete`` False) whose CRC does
    not match its bytes (a corrupt file), or None. Checked before decoding for the same reason as
    ``png_incomplete``: libpng prints "libpng error: IDAT: CRC error" on stderr first (~2 ms for a 1.5 MB sweep)."""
    chunks = _png_chunks(data) if chunks is None else chunks
    view = memoryview(data)
    for kind, start, end in chunks:
        if end + 4 > len(data):
            return None  # truncated: png_incomplete's to tell
        if zlib.crc32(view[start - 4:end]) != int.from_bytes(view[end:end + 4], "big"):  # type + data
            return kind.decode("latin-1", "replace")
    return None


#: Channels per pixel of each PNG colour type (greyscale, RGB, palette, greyscale+alpha, RGBA).
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
#: Bit depths the PNG standard allows per colour type; anything else is a corrupt header.
_PNG_BIT_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
#: Adam7 passes: (first column, first row, column step, row step).
_ADAM7_PASSES = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))
#: Compressed bytes fed to zlib per call, and most bytes one call may return: a bomb's 1000:1 runs of zeros
#: come out in pieces of this size, never at once.
_INFLATE_STEP = 1 << 18
#: Most bytes the compressed text chunks (zTXt, compressed iTXt) of one PNG may inflate to, together. libpng
#: inflates each such chunk up to 8 MB (its per-chunk limit) before the image is decoded: 200 zTXt chunks of
#: 8 KB, each 7 MB of zeros, took 7 s of CPU in ``cv2.imdecode``; radar scans carry no text at all.
MAX_PNG_TEXT_BYTES = 1 << 20


#: Most chunks an uploaded PNG may have. Each costs a step of the Python chunk walks here: a 6.6 MB PNG of 1-byte
#: IDAT chunks (509,321 of them) took 1.9 s to check; a Navtech sweep written by libpng (8 kB IDAT chunks) has
#: 60-200, one of 1.6 M pixels in 1 kB chunks ~1,600.
MAX_PNG_CHUNKS = 10_000
#: Chunks of a PNG decoded here rather than by libpng: anything else (transparency, gamma, palette, text ...)
#: might change what libpng returns, so such files go to OpenCV.
_PLAIN_PNG_CHUNKS = frozenset({b"IHDR", b"IDAT", b"IEND"})


def png_image_data_size(width: int, height: int, bit_depth: int, color_type: int, interlaced: bool) -> int:
    """Bytes a PNG's IDAT stream must inflate to: one filter-type byte per row plus the row's packed pixels, for
    the whole image or, interlaced (Adam7), for each of the 7 passes' sub-images (empty passes have no rows)."""
    bits = bit_depth * _PNG_CHANNELS[color_type]

    def rows_bytes(cols: int, rows: int) -> int:
        return rows * (1 + (cols * bits + 7) // 8) if cols > 0 and rows > 0 else 0

    if not interlaced:
        return rows_bytes(width, height)
    return sum(rows_bytes((width - x0 + dx - 1) // dx, (height - y0 + dy - 1) // dy)
               for x0, y0, dx, dy in _ADAM7_PASSES)


@dataclass(frozen=True)
class _PngImageData:
    """A PNG's IHDR fields and chunks, and its inflated IDAT stream when it was kept.

    Attributes:
        width, height, bit_depth, color_type, interlaced: the IHDR's fields.
        chunks: (type, first data byte, end of data) of every chunk up to IEND.
        rows: the inflated image data (``png_image_data_size`` bytes: a filter byte, then the row's pixels, per
            row), or None when it was not kept.
        stream_ended: the zlib stream ended (adler-32 checked) right after the image data.
    """

    width: int
    height: int
    bit_depth: int
    color_type: int
    interlaced: bool
    chunks: list[tuple[bytes, int, int]]
    rows: bytearray | None
    stream_ended: bool


def _png_chunks(data: bytes) -> list[tuple[bytes, int, int]]:
    """(type, first data byte, end of data) of each chunk up to IEND (the last ones may lie beyond the end of a
    truncated file: ``png_incomplete`` tells).

    Raises:
        ScanFormatError: more than ``MAX_PNG_CHUNKS`` chunks (the walk stops there).
    """
    chunks: list[tuple[bytes, int, int]] = []
    pos = len(PNG_SIGNATURE)
    while pos + 8 <= len(data):
        if len(chunks) == MAX_PNG_CHUNKS:
            raise ScanFormatError(f"upload is not a readable PNG image: more than {MAX_PNG_CHUNKS:,} chunks (a "
                                  "Navtech PNG has a few hundred at most; write it with larger image-data chunks)")
        length = int.from_bytes(data[pos:pos + 4], "big")
        kind = bytes(data[pos + 4:pos + 8])
        chunks.append((kind, pos + 8, pos + 8 + length))
        if kind == b"IEND":
            break
        pos += 12 + length
    return chunks


def _text_payload(kind: bytes, body: memoryview) -> memoryview | None:
    """The zlib stream of a zTXt chunk or of a compressed iTXt chunk, or None (uncompressed, or malformed: libpng
    skips those with a warning). zTXt: keyword NUL method data; iTXt: keyword NUL flag method language NUL
    translated keyword NUL text."""
    raw = bytes(body)  # at most the upload's size; text chunks are rare (Navtech scans have none)
    key_end = raw.find(b"\0", 0, 80)
    if key_end < 1:
        return None
    if kind == b"zTXt":
        return body[key_end + 2:]
    if raw[key_end + 1:key_end + 2] != b"\x01":  # iTXt compression flag 0: plain text, nothing to inflate
        return None
    lang_end = raw.find(b"\0", key_end + 3)
    trans_end = raw.find(b"\0", lang_end + 1) if lang_end >= 0 else -1
    return body[trans_end + 1:] if trans_end >= 0 else None


def _inflate_bounded(pieces: list[memoryview], limit: int, out: bytearray | None = None) -> tuple[int, bool]:
    """Inflate the zlib stream split over ``pieces`` up to its end, stopping as soon as more than ``limit``
    bytes came out; returns (bytes produced, at most ``limit`` + 1; whether the stream ended). The output is
    copied into ``out`` (``limit`` bytes long) when given, else dropped at once: one call returns at most
    ``_INFLATE_STEP`` bytes.

    Raises:
        zlib.error: a corrupt stream (or a wrong adler-32 at its end).
    """
    inflater = zlib.decompressobj()
    produced = 0
    for piece in pieces:
        for pos in range(0, len(piece), _INFLATE_STEP):
            buf: bytes | memoryview = piece[pos:pos + _INFLATE_STEP]
            while buf and not inflater.eof:
                chunk = inflater.decompress(buf, min(_INFLATE_STEP, limit + 1 - produced))
                if produced + len(chunk) > limit:
                    return limit + 1, False
                if out is not None:
                    out[produced:produced + len(chunk)] = chunk
                produced += len(chunk)
                buf = inflater.unconsumed_tail  # non-empty only when the output bound stopped the call
            if inflater.eof:  # bytes after the stream's end are never inflated (libpng ignores them too)
                return produced, True
    return produced, False


def _checked_png_image_data(data: bytes, keep: bool,
                            chunks: list[tuple[bytes, int, int]] | None = None) -> _PngImageData:
    """``check_png_image_data``; with ``keep`` the inflated image data of a PNG ``_plain_png_pixels`` may decode
    (8-bit greyscale, not interlaced, IHDR / IDAT / IEND chunks only) is returned too. ``chunks``: the file's
    ``_png_chunks``, when the caller walked them already."""
    chunks = _png_chunks(data) if chunks is None else chunks
    if not chunks or chunks[0][0] != b"IHDR" or chunks[0][2] - chunks[0][1] != 13:
        raise ScanFormatError("upload is not a readable PNG image (corrupt or truncated header)")
    width, height, depth, color, _, _, interlace = struct.unpack(">IIBBBBB", data[chunks[0][1]:chunks[0][2]])
    if width == 0 or height == 0 or depth not in _PNG_BIT_DEPTHS.get(color, ()) or interlace > 1:
        raise ScanFormatError("upload is not a readable PNG image (corrupt header)")
    view = memoryview(data)
    expected = png_image_data_size(width, height, depth, color, interlace == 1)
    idat = [view[start:end] for kind, start, end in chunks if kind == b"IDAT"]
    if not idat:
        raise ScanFormatError("upload is not a readable PNG image (corrupt: no image data)")
    plain = depth == 8 and color == 0 and interlace == 0 and all(kind in _PLAIN_PNG_CHUNKS for kind, _, _ in chunks)
    rows = bytearray(expected) if keep and plain else None  # only what _plain_png_pixels can decode is kept
    try:
        produced, ended = _inflate_bounded(idat, expected, rows)
    except zlib.error:
        raise ScanFormatError("upload is not a readable PNG image (corrupt compressed image data)") from None
    if produced > expected:
        raise ScanFormatError(
            f"upload is not a readable PNG image: its compressed image data inflates to more than the "
            f"{expected:,} bytes its {height} x {width} header declares (a decompression bomb, or a corrupt file)")
    if produced < expected:
        raise ScanFormatError(f"upload is not a readable PNG image (corrupt or truncated: its image data ends "
                              f"after {produced:,} of the {expected:,} bytes its {height} x {width} header declares)")
    text_budget = MAX_PNG_TEXT_BYTES
    for kind, start, end in chunks:
        payload = _text_payload(kind, view[start:end]) if kind in (b"zTXt", b"iTXt") else None
        if payload is None:
            continue
        try:
            text_bytes, _ = _inflate_bounded([payload], text_budget)
        except zlib.error:  # libpng skips a corrupt text chunk with a warning: nothing to bound
            continue
        if text_bytes > text_budget:
            raise ScanFormatError(
                f"upload is not a readable PNG image: its compressed text chunks (zTXt / iTXt) inflate to more "
                f"than {MAX_PNG_TEXT_BYTES // 2**20} MiB (a decompression bomb; a radar scan needs no text)")
        text_budget -= text_bytes
    return _PngImageData(width, height, depth, color, interlace == 1, chunks, rows, ended)


def check_png_image_data(data: bytes) -> None:
    """Refuse a complete PNG (``png_incomplete`` is False) whose compressed data would inflate to more than its
    header allows, before any decoder sees it: libpng (OpenCV's PNG reader) inflates an IDAT stream to its end,
    image rows or not, so a 7.7 MB PNG with ~7 GB of zeros after its 400 rows took 17-19 s of CPU in
    ``cv2.imdecode`` and was then decoded.

    The IDAT stream is inflated with its output bounded by the size the IHDR implies (``png_image_data_size``:
    height x (1 + row bytes), summed over the Adam7 passes when interlaced) plus one byte, so a bomb costs at
    most one image's worth of inflating (~5 ms for a Navtech sweep); compressed text chunks likewise, within
    ``MAX_PNG_TEXT_BYTES`` together.

    Raises:
        ScanFormatError: a corrupt IHDR, no image data, image data that inflates to more or fewer bytes than the
            header declares or is not a valid zlib stream, text chunks beyond ``MAX_PNG_TEXT_BYTES``.
    """
    _checked_png_image_data(data, keep=False)


def _plain_png_pixels(data: bytes, png: _PngImageData) -> np.ndarray | None:
    """(H, W) uint8 pixels of a PNG whose image data ``_checked_png_image_data`` kept, when it is an 8-bit
    greyscale, non-interlaced image of IHDR / IDAT / IEND chunks only, every chunk's CRC right, its zlib stream
    complete and every row filtered None, Sub or Up (OpenCV writes Sub rows: every Navtech PNG the simulator and
    the clients encode); None otherwise, for ``cv2.imdecode`` to decode. The same pixels as libpng (tested),
    without inflating the data a second time: the bomb check costs nothing on these files."""
    if png.rows is None or not png.stream_ended:  # not plain (see _checked_png_image_data), or no zlib end
        return None
    view = memoryview(data)
    for _, start, end in png.chunks:  # libpng refuses a critical chunk with a wrong CRC: so does this path
        if zlib.crc32(view[start - 4:end]) != int.from_bytes(view[end:end + 4], "big"):
            return None
    rows = np.frombuffer(png.rows, dtype=np.uint8).reshape(png.height, png.width + 1)
    filters, filtered = rows[:, 0], rows[:, 1:]
    out = np.empty((png.height, png.width), dtype=np.uint8)
    if np.all(filters == 1):  # Sub (bytes per pixel 1): each byte adds the one before it, modulo 256
        np.cumsum(filtered, axis=1, dtype=np.uint8, out=out)
        return out
    if np.any(filters > 2):  # Average / Paeth rows depend on their left neighbour's sum: libpng's job
        return None
    previous = np.zeros(png.width, dtype=np.uint8)
    for r in range(png.height):
        if filters[r] == 0:
            out[r] = filtered[r]
        elif filters[r] == 1:
            np.cumsum(filtered[r], dtype=np.uint8, out=out[r])
        else:  # Up: adds the row above (zeros above the first row)
            np.add(filtered[r], previous, out=out[r])
        previous = out[r]
    return out


def check_png_sides(data: bytes, name: str) -> None:
    """Refuse a PNG file whose header declares more than ``MAX_SCAN_SIDE`` rows or columns (plus the Navtech metadata
    columns) before it is decoded: a 74-byte PNG declaring 100,000 x 100,000 pixels ended in OpenCV's traceback
    (QA session 38). Files that are not PNGs, or lack the header, are left to the decoder's own checks.

    Raises:
        ScanTooLargeError: naming ``name`` and the declared size.
    """
    if len(data) < 24 or data[:8] != PNG_SIGNATURE or data[12:16] != b"IHDR":
        return
    cols, rows = struct.unpack(">II", data[16:24])
    if rows > MAX_SCAN_SIDE or cols > MAX_SCAN_SIDE + NAVTECH_META_COLUMNS:
        raise ScanTooLargeError(f"{name}: declares {rows} x {cols} pixels; a radar scan has at most {MAX_SCAN_SIDE} "
                                f"azimuths and {MAX_SCAN_SIDE} range bins (a Navtech sweep is 400 x 3,371-3,779)")


def read_navtech_png(path: str | Path, preset: str | RadarPreset | None = None) -> RadarScan:
    """Read a Navtech polar PNG (layout in the module docstring).

    Args:
        path: the PNG file.
        preset: radar preset giving range resolution/offset; inferred from the bin count when None.

    Raises:
        ScanFormatError: unreadable file, wrong bit depth or shape (message names the file).
    """
    import cv2

    path = Path(path)
    if path.is_dir():  # e.g. a folder named like a scan inside radar/ (QA)
        raise ScanFormatError(f"{path}: is a folder, not a scan file")
    if not path.is_file():
        raise ScanFormatError(f"{path}: no such scan file")
    data = path.read_bytes()
    if not data:  # cv2.imdecode asserts on an empty buffer (QA session 40: a traceback, the file unnamed)
        raise ScanFormatError(f"{path}: empty file (0 bytes), not a scan")
    check_png_file(data, str(path))
    check_png_sides(data, str(path))
    raw = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ScanFormatError(f"{path}: not a readable PNG image")
    return _scan_from_raw(raw, preset, str(path))


def decode_navtech_png_bytes(data: bytes, preset: str | RadarPreset | None = None,
                             map_preset: str | RadarPreset | None = None) -> RadarScan:
    """Decode a Navtech PNG held in memory (e.g. an upload); see ``read_navtech_png``. Only PNG is decoded:
    OpenCV would read JPEG and other lossy images too. Without ``preset``, ``map_preset`` (the preset of the
    map the scan is localized on) is used when its bin count fits (``_upload_preset``)."""
    import cv2

    if data[:8] != PNG_SIGNATURE:
        raise ScanFormatError("upload is not a readable PNG image (corrupt or truncated: no PNG signature)")
    chunks = _png_chunks(data)  # one walk, bounded by MAX_PNG_CHUNKS, for both checks below
    if png_incomplete(data, chunks):
        raise ScanFormatError("upload is not a readable PNG image (corrupt or truncated: it ends before the PNG's last chunk)")
    # uploads and archive scans: a decompression bomb is refused before libpng sees it, and the inflated rows of
    # a plain 8-bit PNG are decoded here (not inflated twice); files read from disk (read_navtech_png) are trusted
    raw = _plain_png_pixels(data, _checked_png_image_data(data, keep=True, chunks=chunks))
    if raw is None:
        raw = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ScanFormatError("upload is not a readable PNG image (corrupt or truncated)")
    return _scan_from_raw(raw, preset, "upload", lambda n: _upload_preset(n, map_preset))


def encode_navtech_png_bytes(scan: RadarScan) -> bytes:
    """Encode a scan as Navtech PNG bytes (power quantised to uint8)."""
    import cv2  # here, not at import: reading an .npy header (``reradar localize``) needs no OpenCV

    ok, buf = cv2.imencode(".png", _raw_from_scan(scan))
    if not ok:  # pragma: no cover - OpenCV only fails on impossible shapes
        raise ScanFormatError("could not encode scan as PNG")
    return buf.tobytes()


def write_navtech_png(scan: RadarScan, path: str | Path) -> Path:
    """Write ``scan`` as a Navtech PNG (power quantised to uint8). Returns the path written."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(encode_navtech_png_bytes(scan))
    return path


def read_polar_npy(path: str | Path | None = None, preset: str | RadarPreset | None = None,
                   array: np.ndarray | None = None) -> RadarScan:
    """Read a plain (A, R) polar array saved with ``np.save`` (uint8 0..255 or float in [0, 1]).

    Azimuths are assumed uniform from 0; range geometry comes from ``preset``, inferred from the range-bin count
    when None (``infer_preset``: refused when ambiguous). The shape is checked against the preset
    (``check_polar_shape``).
    """
    source = "upload" if path is None else str(path)
    if array is None:
        if path is None:
            raise ScanFormatError("read_polar_npy needs a path or an array")
        try:
            array = np.load(Path(path), allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            raise ScanFormatError(f"{path}: not a readable .npy array ({exc})") from exc
    if array.dtype.kind not in "uif":
        raise ScanFormatError(f"{source}: polar array must be numeric, got dtype {array.dtype}")
    if array.ndim != 2:
        raise ScanFormatError(f"{source}: polar array must be 2-D (azimuths x range bins), got shape {array.shape}")
    p = get_preset(preset) if preset is not None else infer_preset(array.shape[1], source)
    check_polar_shape(array.shape[0], array.shape[1], p, source)
    if array.dtype != np.uint8:
        array = array.astype(np.float32)
        if array.size and np.all(np.isfinite(array)) and (array.min() < 0 or array.max() > 1):
            raise ScanFormatError(f"{source}: a non-uint8 polar array must hold power as fractions of full scale "
                                  "in [0, 1] (uint8 arrays hold 0..255); rescale it first (e.g. divide 16-bit data "
                                  "by 65535)")
    return RadarScan.from_power(array, p)


def read_navtech_npy(path: str | Path, preset: str | RadarPreset | None = None) -> RadarScan:
    """Read an .npy holding a Navtech PNG's pixels (``np.save`` of the image: uint8 (A, 11 + R), the metadata
    columns, then the range bins): the same scan as the PNG, checked as the PNG is (``check_navtech_layout``).
    The preset is inferred from the range-bin count when None (``infer_preset``: refused when ambiguous).

    Raises:
        ScanFormatError: unreadable file, another dtype or shape, metadata that is no Navtech sweep's (message
            names the file).
    """
    path = Path(path)
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise ScanFormatError(f"{path}: not a readable .npy array ({exc})") from exc
    if array.dtype != np.uint8 or array.ndim != 2:
        raise ScanFormatError(f"{path}: a Navtech .npy must be a 2-D uint8 array of the PNG's pixels, got dtype "
                              f"{array.dtype} shape {array.shape}")
    return _scan_from_raw(array, preset, str(path))


def load_scan(path: str | Path, preset: str | RadarPreset | None = None,
              npy_layout: NpyLayout = "polar") -> RadarScan:
    """Read a scan by suffix: ``.png`` Navtech PNG, ``.npy`` polar array (``npy_layout`` ``polar``) or the Navtech
    PNG's pixels (``navtech``: ``read_navtech_npy``); the preset is inferred from the range-bin count when None and
    refused when that count is ambiguous (``infer_preset``)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if npy_layout not in ("polar", "navtech"):
        raise ScanFormatError(f"unknown .npy layout {npy_layout!r}; choose polar or navtech")
    if suffix == ".png":
        return read_navtech_png(path, preset)
    if suffix == ".npy":
        return read_navtech_npy(path, preset) if npy_layout == "navtech" else read_polar_npy(path, preset)
    raise ScanFormatError(f"{path}: unsupported scan format {suffix!r} (use .png or .npy)")


def _npy_from_bytes(data: bytes) -> np.ndarray:
    """An uploaded .npy (no pickles), or a ``ScanFormatError`` that says why it is not one."""
    try:
        return np.load(io.BytesIO(data), allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise ScanFormatError(f"upload is not a readable .npy array ({exc})") from exc


def decode_navtech_npy_bytes(data: bytes, preset: str | RadarPreset | None = None,
                             map_preset: str | RadarPreset | None = None) -> RadarScan:
    """Decode an .npy array holding a Navtech PNG's pixels (uint8 (A, 11 + R): the metadata columns, then the
    range bins) - the same scan as the PNG, with the same azimuths and timestamps, without PNG's inflate
    (~5-10 ms per sweep) for 2.7x the bytes (``NpyLayout`` ``navtech``)."""
    array = _npy_from_bytes(data)
    if array.dtype != np.uint8 or array.ndim != 2:
        raise ScanFormatError(f"a Navtech .npy (scan_layout navtech) must be a 2-D uint8 array of the PNG's pixels, "
                              f"got dtype {array.dtype} shape {array.shape}")
    return _scan_from_raw(array, preset, "upload", lambda n: _upload_preset(n, map_preset))


#: What an uploaded .npy holds: ``polar`` = (A, R) power, uniform azimuths, geometry from the preset;
#: ``navtech`` = the Navtech PNG's pixels, metadata columns included (decoded exactly as the PNG).
NpyLayout = Literal["polar", "navtech"]


def load_scan_bytes(data: bytes, filename: str = "scan.png", preset: str | RadarPreset | None = None,
                    npy_layout: NpyLayout = "polar", map_preset: str | RadarPreset | None = None) -> RadarScan:
    """Decode an uploaded scan by its filename suffix (``.png`` or ``.npy``; an .npy as ``npy_layout``).

    Without ``preset`` the geometry comes from ``map_preset`` (the preset of the map the scan is localized on)
    where the scan fits it: always for a polar .npy (which carries no geometry; oxford without a map), and for
    a Navtech PNG / .npy whose bin count is the map preset's (else the first preset with that count)."""
    suffix = Path(filename).suffix.lower()
    if suffix == ".npy":
        if npy_layout == "navtech":
            return decode_navtech_npy_bytes(data, preset, map_preset)
        return read_polar_npy(array=_npy_from_bytes(data), preset=preset or map_preset or "oxford")
    if suffix in (".png", ""):
        return decode_navtech_png_bytes(data, preset, map_preset)
    raise ScanFormatError(f"unsupported scan format {suffix!r} (upload a Navtech .png or a polar .npy)")
