"""``reradar import-scans``: convert polar scans of another layout or resolution into Navtech PNGs."""

from __future__ import annotations

import logging
import math
import os
import re
import shutil
from pathlib import Path

import numpy as np
import typer

from reradar_core.errors import ReRadarError, ScanFormatError
from reradar_core.io.scan import PNG_SIGNATURE, check_png_file, check_png_sides, has_navtech_metadata

logger = logging.getLogger(__name__)

#: File names read as timestamps: 16 digits = microseconds (Boreas, Oxford), 19 digits = nanoseconds (MulRan).
_TIMESTAMP_DIGITS = {16: 1, 19: 1000}


def _stamp_us(src: Path, k: int) -> int:
    """The output timestamp (µs) of source ``src``, the ``k``-th in name order: its name when that is a µs or ns
    timestamp; ``(k + 1)`` seconds for non-numeric names. Other all-digit names are ambiguous and refused."""
    stem = src.stem
    if not (stem.isascii() and stem.isdigit()):
        return (k + 1) * 1_000_000
    if len(stem) not in _TIMESTAMP_DIGITS:
        raise ScanFormatError(f"{src.name}: a {len(stem)}-digit numeric name is not a timestamp this command reads "
                              "(16 digits = microseconds, 19 = nanoseconds); rename the scans to one of those forms, "
                              "or to non-numeric names to number them 1 s apart")
    return int(stem) // _TIMESTAMP_DIGITS[len(stem)]


def natural_key(path: Path) -> tuple:
    """Sort key of ``path`` in natural (numeric-aware) name order: ``scan_9`` before ``scan_10``; the folder
    first, then the name's digit runs by value and the rest as text."""
    parts = re.split(r"(\d+)", path.name)
    return (str(path.parent), tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in parts if p))


def describe_geometry(shape: tuple[int, int], transposed: bool, resolution_m: float, offset_m: float) -> str:
    """What ``import-scans`` takes a source of array ``shape`` (rows, columns) to be: azimuths, range bins, bin
    size and maximum range in metres."""
    n_az, n_bins = (shape[1], shape[0]) if transposed else shape
    axes = "columns = azimuths, rows = range bins (--transposed)" if transposed else \
        "rows = azimuths, columns = range bins"
    return (f"{n_az} azimuths x {n_bins} range bins ({axes}), {resolution_m:g} m/bin from {offset_m:g} m: "
            f"maximum range {offset_m + (n_bins - 1) * resolution_m:.1f} m")


def orientation_hint(shape: tuple[int, int], transposed: bool) -> str | None:
    """A warning when the assumed orientation looks swapped: polar radar scans have more range bins than
    azimuths (Navtech 400 x 3,360; Oxford 400 x 3,768), so more azimuths than range bins suggests the other
    axis order. None when nothing looks wrong."""
    n_az, n_bins = (shape[1], shape[0]) if transposed else shape
    if n_az <= n_bins:
        return None
    fix = "drop --transposed" if transposed else "pass --transposed"
    return (f"warning: read as {n_az} azimuths x {n_bins} range bins, but radar scans have more range bins than "
            f"azimuths (e.g. 400 x 3360): if the source's {'columns' if transposed else 'rows'} are range bins, "
            f"{fix}")


def _mapping_lines(sources: list[Path], stamps: list[int], show_all: int = 10) -> list[str]:
    """``source -> output name`` lines: all of them when there are at most ``show_all``, else the first three and
    the last two."""
    pairs = [f"  {src} -> {stamp}.png" for src, stamp in zip(sources, stamps, strict=True)]
    if len(pairs) <= show_all:
        return pairs
    return pairs[:3] + [f"  ... ({len(pairs) - 5} more)"] + pairs[-2:]


#: Sample depths ``--bit-depth`` accepts, bits: full scale ``2**bits - 1`` (8: 255, 12: 4095, 16: 65535)
BIT_DEPTH_RANGE = (1, 16)


def full_scale(bit_depth: int) -> int:
    """The largest raw sample of ``bit_depth``-bit data (``2**bit_depth - 1``): the value that is power 1.0."""
    lo, hi = BIT_DEPTH_RANGE
    if not lo <= bit_depth <= hi:
        raise ScanFormatError(f"--bit-depth {bit_depth}: give the radar's sample depth in bits, {lo} to {hi}")
    return (1 << bit_depth) - 1


def _container_bits(dtype: np.dtype) -> int:
    """Bits of non-negative values an integer ``dtype`` holds: 8 for uint8, 15 for int16, 16 for uint16."""
    return dtype.itemsize * 8 - (1 if dtype.kind == "i" else 0)


def scale_to_unit_power(array: np.ndarray, name: str, bit_depth: int | None = None,
                        from_png: bool = True) -> np.ndarray:
    """A source scan's raw samples as power in [0, 1] (fractions of full scale), or the array unchanged when
    the importer reads it as it is.

    With ``bit_depth`` (``--bit-depth``): integer samples (a PNG's or an integer .npy's) divided by
    ``full_scale(bit_depth)`` as float32, e.g. 12-bit 4095 -> 1.0 and 1365 -> 1/3. Refused (``ScanFormatError``
    naming ``name``, the file): floating-point samples (already a fraction, or of no known scale), a depth
    larger than the array's type holds (12-bit samples in an 8-bit PNG), negative samples, and samples above
    the full scale (the data holds more bits than declared).

    Without it, as before the option: a 16-bit PNG (uint16, ``from_png``) is read at the 16-bit full scale
    (65535), with a warning naming ``--bit-depth`` when its values reach only 12 bits or fewer; uint8 (0-255) and
    floats in [0, 1] are left to ``import_polar_scan``; other integer samples above 1 (an .npy's) are refused,
    naming ``--bit-depth``.
    """
    if bit_depth is None:
        if from_png and array.dtype == np.uint16:  # full scale of a 16-bit greyscale image
            top = int(array.max()) if array.size else 0
            if 0 < top < 4096:
                # e.g. 12-bit samples in a 16-bit PNG: scaled by 65535 they keep ~1/16 of their levels (QA session 38)
                logger.warning("%s: a 16-bit PNG whose values reach only %d (12 bits or fewer of 16): read at the "
                               "16-bit full scale (65535) its power is dark and coarse; if the radar wrote fewer "
                               "bits, pass its sample depth, e.g. --bit-depth 12 (full scale 4095)", name, top)
            return array.astype(np.float32) / 65535.0
        if array.dtype.kind in "iu" and array.dtype != np.uint8 and array.size and int(array.max()) > 1:
            raise ScanFormatError(f"{name}: integer samples up to {int(array.max())} ({array.dtype}) with no "
                                  "stated full scale: pass the radar's sample depth, e.g. --bit-depth 12 (full "
                                  "scale 4095), or save the power as floats in [0, 1]")
        return array
    scale = full_scale(bit_depth)
    if array.dtype.kind not in "iu":
        raise ScanFormatError(f"{name}: holds {array.dtype} samples; --bit-depth scales integer samples (a PNG's "
                              "or an integer .npy's): drop --bit-depth for power already in [0, 1], or save the "
                              "raw samples as integers")
    held = _container_bits(array.dtype)
    if bit_depth > held:
        kind = f"the PNG has {held} bits" if from_png else f"the array ({array.dtype}) holds at most {held} bits"
        raise ScanFormatError(f"{name}: {kind} per sample, too few for {bit_depth}-bit samples (--bit-depth "
                              f"{bit_depth}): pass --bit-depth {held} or less (the radar's sample depth), or drop it")
    if not array.size:
        return array.astype(np.float32)
    low, top = int(array.min()), int(array.max())
    if low < 0:
        raise ScanFormatError(f"{name}: a sample is {low}; radar power is not negative: check the source")
    if top > scale:
        raise ScanFormatError(f"{name}: a sample reaches {top}, above the {bit_depth}-bit full scale {scale} "
                              f"(--bit-depth {bit_depth}): the samples have more bits; pass the radar's sample depth "
                              f"(at least --bit-depth {top.bit_length()})")
    return (array.astype(np.float64) / scale).astype(np.float32)


def _read_source(src: Path, bit_depth: int | None = None) -> np.ndarray:
    """A source scan as a 2-D array: an .npy, or a greyscale (8- or 16-bit) PNG; refuses colour images and scans
    that already are Navtech scans (their 11 metadata columns would be read as range bins). Integer samples are
    scaled to power in [0, 1] by ``scale_to_unit_power`` (``bit_depth``: ``--bit-depth``)."""
    import cv2

    if src.is_dir():
        raise ScanFormatError(f"{src}: is a folder; pass its scans (e.g. {src}/*.png)")
    if not src.is_file():
        raise ScanFormatError(f"{src}: no such file")
    if src.suffix.lower() == ".npy":
        try:
            array = np.load(src, allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            raise ScanFormatError(f"{src.name}: not a readable .npy array ({exc})") from None
    else:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)  # its warnings would repeat the error below
        data = src.read_bytes()
        if not data:  # cv2.imdecode asserts on an empty buffer (QA session 40: a traceback, the file unnamed)
            raise ScanFormatError(f"{src.name}: empty file (0 bytes), not a scan")
        if data[:8] == PNG_SIGNATURE:  # told before libpng reads it (it prints its own "libpng error" line otherwise)
            check_png_file(data, src.name)
            check_png_sides(data, src.name)
        array = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if array is None:
            raise ScanFormatError(f"{src.name}: not a readable image")
        if array.ndim == 3:
            raise ScanFormatError(f"{src.name}: a {array.shape[2]}-channel colour image; import-scans reads "
                                  "single-channel (greyscale) power images: save the radar's power as greyscale")
    if has_navtech_metadata(array):
        raise ScanFormatError(f"{src.name}: already a Navtech scan (its first 11 columns are Navtech timestamps, "
                              "encoder values and valid flags); it needs no import: read it directly (reradar info, "
                              "build-map, localize) with the --preset it was recorded with")
    if array.ndim != 2:  # said by import_polar_scan, with the shape
        return array
    return scale_to_unit_power(array, src.name, bit_depth, from_png=src.suffix.lower() != ".npy")


def _discard(staging: Path, created_out: Path | None) -> None:
    """Remove an import's staging folder, and --out itself when the import created it and it is empty again."""
    shutil.rmtree(staging, ignore_errors=True)
    if created_out is not None:
        try:
            created_out.rmdir()  # only when empty
        except OSError:
            pass


def register(app: typer.Typer) -> None:
    @app.command("import-scans")
    def import_scans(
        sources: list[Path] = typer.Argument(..., help="Foreign polar scans: single-channel (greyscale) PNG without "
                                             "Navtech metadata, or .npy."),
        out: Path = typer.Option(..., "--out", help="Folder for the Navtech PNGs (created)."),
        overwrite: bool = typer.Option(False, "--overwrite", help="Replace scans already in --out that have the "
                                       "same names (timestamps)."),
        range_resolution: float = typer.Option(..., "--range-resolution",
                                               help="Metres per range bin of the SOURCE scans (e.g. 0.175)."),
        preset: str = typer.Option("boreas", help="Target radar preset (boreas, boreas-2021, oxford, oord, mulran)."),
        range_offset: float = typer.Option(0.0, "--range-offset", help="Range of the source's bin 0, metres."),
        transposed: bool = typer.Option(False, "--transposed",
                                        help="Source rows are range bins and columns azimuths."),
        start_azimuth_deg: float = typer.Option(0.0, "--start-azimuth-deg",
                                                help="Azimuth of the first source beam, degrees clockwise."),
        bit_depth: int | None = typer.Option(
            None, "--bit-depth", min=BIT_DEPTH_RANGE[0], max=BIT_DEPTH_RANGE[1], help=(
                "Bits per sample the radar wrote, when its integer samples (a 16-bit PNG's, an integer .npy's) "
                "do not fill their type: power = value / (2^bits - 1), e.g. 12 for 12-bit data in a 16-bit PNG "
                "(4095 = full power). A sample above that full scale, or more bits than the file's type holds, is "
                "refused. Default: 8-bit PNGs / 255, 16-bit PNGs / 65535, .npy floats in [0, 1] as they are.")),
    ) -> None:
        """Resample foreign polar scans onto a preset's range grid and write them as Navtech PNGs.

        Output names are microsecond timestamps. Source names are read as timestamps when they are 16 digits
        (microseconds, Boreas / Oxford) or 19 digits (nanoseconds, MulRan; converted to microseconds); other
        numeric names are refused as ambiguous; non-numeric names are numbered 1, 2, 3, ... seconds from 0 in name
        order (give sequences timestamped names to keep their timing); a mix of the three kinds of names is
        refused. Name order is natural (numeric-aware): scan_9 comes before scan_10. The command prints the
        geometry it assumes for the sources (azimuths, range bins, bin size, maximum range) and which source
        became which output name. Sources that would get the same output name, or the name of a scan already in
        --out (unless --overwrite), are refused.

        Power: an 8-bit source is read as value / 255 and a 16-bit PNG as value / 65535 (a warning names
        --bit-depth when its values reach 12 bits or fewer); --bit-depth N reads integer samples as value / (2^N - 1)
        and refuses a sample above that full scale. Nothing is written unless every source converts.

        Read the output with `reradar info` or `localize`. It holds scans only: for `build-map --dataset` or
        `bench`, put them in a sequence folder as SEQ/radar/<t_us>.png and add a pose file with one pose per
        scan time (SEQ/applanix/radar_poses.csv in the Boreas layout: GPSTime,easting,northing,...,heading;
        relative times need --time-unit), and pass the --preset used here (a Boreas folder must name its preset).
        """
        from reradar_core.io.importer import ForeignScanLayout, import_polar_scan
        from reradar_core.io.scan import write_navtech_png
        from reradar_core.paths import output_dir

        try:
            layout = ForeignScanLayout(range_resolution, range_offset, 1 if transposed else 0,
                                       math.radians(start_azimuth_deg))
            ordered = sorted(sources, key=natural_key)
            seen: dict[Path, Path] = {}
            for src in ordered:  # one scan given twice would become two scans of one sweep, a second apart
                other = seen.setdefault(src.resolve(), src)
                if other is not src:
                    raise ScanFormatError(f"{src} is given twice (also as {other}); give each scan once")
            kind_of = {src: len(src.stem) if src.stem.isascii() and src.stem.isdigit() else "name" for src in ordered}
            by_kind: dict[object, list[Path]] = {}
            for src in ordered:
                by_kind.setdefault(kind_of[src], []).append(src)
            if len(by_kind) > 1:  # e.g. scanA.png (numbered 1 s, 1970) among 2019 timestamps
                # the fewest (on a tie, the non-timestamp names): most likely the strays
                odd = min(by_kind.items(), key=lambda kv: (len(kv[1]), kv[0] != "name"))[1]
                label = {16: "16-digit µs timestamps", 19: "19-digit ns timestamps", "name": "other names"}
                counts = ", ".join(f"{len(v)} with {label.get(k, f'{k}-digit numbers')}" for k, v in by_kind.items())
                raise ScanFormatError(f"the sources mix kinds of names ({counts}); one sequence takes one kind: "
                                      f"rename or leave out {', '.join(str(p) for p in odd[:3])}"
                                      f"{' ...' if len(odd) > 3 else ''}, or import them separately")
            stamps = [_stamp_us(src, k) for k, src in enumerate(ordered)]
            clashes: dict[int, list[str]] = {}
            for src, stamp in zip(ordered, stamps, strict=True):
                clashes.setdefault(stamp, []).append(str(src))
            clashing = [names for names in clashes.values() if len(names) > 1]
            if clashing:
                shown = "; ".join(" and ".join(names) for names in clashing[:3])
                raise ScanFormatError(f"sources with the same timestamp would overwrite each other's output: {shown}"
                                      f"{' ...' if len(clashing) > 3 else ''}; import them into separate folders")
            output_dir(out, "--out", create=False)  # created only when the first scan converts
            existing = [f"{stamp}.png" for stamp in stamps if (out / f"{stamp}.png").exists()]
            if existing and not overwrite:
                raise ScanFormatError(f"--out {out} already holds {len(existing)} scan(s) of these names "
                                      f"({', '.join(existing[:3])}{' ...' if len(existing) > 3 else ''}); pass "
                                      "--overwrite to replace them, or choose another --out")
            if bit_depth is not None:
                typer.echo(f"power read as {bit_depth}-bit samples: value / {full_scale(bit_depth)} (--bit-depth)")
            written = 0
            shapes: set[tuple[int, int]] = set()
            # every scan is written into a staging folder inside --out and moved in only when all converted, so a
            # source refused half-way leaves --out as it was (QA session 38: the scans before it stayed, and the
            # re-run after the fix was refused for them)
            staging = out / f".reradar-import-{os.getpid()}"
            created_out = not out.exists()
            for src, stamp in zip(ordered, stamps, strict=True):
                try:
                    array = _read_source(src, bit_depth)
                    if array.ndim == 2 and array.shape not in shapes:  # say what each new size is taken to be
                        shapes.add(array.shape)
                        typer.echo(f"{src.name}: read as {describe_geometry(array.shape, transposed, range_resolution, range_offset)}")
                        hint = orientation_hint(array.shape, transposed)
                        if hint:
                            typer.echo(hint, err=True)
                    scan = import_polar_scan(array, layout, preset, start_time_us=stamp)
                except ScanFormatError as exc:
                    msg = str(exc)
                    msg = msg if msg.startswith((src.name, str(src))) else f"{src}: {msg}"
                    if written:
                        msg += f" (nothing was written: {written} scan(s) before it had converted)"
                    _discard(staging, out if created_out else None)
                    raise ScanFormatError(msg) from None
                except BaseException:
                    _discard(staging, out if created_out else None)
                    raise
                if not written:
                    output_dir(staging, "--out")
                write_navtech_png(scan, staging / f"{stamp}.png")
                written += 1
            for stamp in stamps:
                (staging / f"{stamp}.png").replace(out / f"{stamp}.png")
            staging.rmdir()
        except (ReRadarError, OSError, ValueError) as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from exc
        typer.echo(f"wrote {len(sources)} Navtech PNG(s) for preset {preset!r} to {out} (source -> output name, in "
                   "natural name order):")
        for line in _mapping_lines(ordered, stamps):
            typer.echo(line)
