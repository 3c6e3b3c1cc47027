"""Safe extraction of uploaded scan archives (zip / tar / tar.gz / tar.xz / tar.bz2) for map building.

Only regular files named ``<timestamp_us>.png`` or ``<timestamp_us>.npy`` are extracted, flattened into one
folder (directory parts are dropped, so ``../`` tricks cannot escape); links, devices and other files are
ignored (an archive may carry a readme, a poses file or macOS ``._`` files beside its scans), except a file named
like a scan whose timestamp has a sign (``-1000000.png``) or is beyond ``MAX_SCAN_TIMESTAMP_US``: it is meant as
a scan that cannot be one, and is refused by name (400) rather than silently left out of the map. Everything is
bounded before it costs anything: the number of members of any name (``max_archive_members``: a zip's central
directory is counted before ``zipfile`` reads it, a tar's members are read one at a time and not kept), the
bytes all members expand to (skipping a member of a compressed tar decompresses it too), and the number of
scans.

``check_scan_times`` then refuses, before the build starts, two scans of one scan time and a PNG whose file name
and embedded time lie more than one sweep apart: a map keys its keyframes by the time each scan carries (a Navtech
PNG's first azimuth timestamp, a polar .npy's file name), while its pose is taken from the poses file at the time
its file name says, so the two must be one instant (the rule of a sequence folder, ``load_sequence``).
"""

from __future__ import annotations

import logging
import re
import shutil
import struct
import tarfile
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from reradar_core.errors import ScanFormatError
from reradar_core.io.datasets import (
    first_confirmed_problem,
    scan_name_time_mismatch,
    warn_names_off_first_azimuth,
)
from reradar_core.io.datasets import pose_file_reader as datasets_pose_file_reader
from reradar_core.io.poses import PoseSequence
from reradar_core.io.presets import RadarPreset, get_preset
from reradar_core.io.scan import (
    MAX_SCAN_TIMESTAMP_US,
    NAVTECH_META_COLUMNS,
    max_scan_file_bytes,
    navtech_png_first_time_us,
    scan_header,
)
from service.core.errors import BadRequestError, PayloadTooLargeError

logger = logging.getLogger(__name__)

__all__ = ["extract_scan_archive", "check_scan_times", "check_scan_layouts", "scan_time_us", "navtech_png_scan_time_us",
           "duplicate_scan_time_message", "scan_name_time_message", "SWEEP_PRESET",
           "max_archive_members", "zip_entries_exceed", "SCAN_NAME_PATTERN",
           "MAX_SCAN_TIMESTAMP_US", "ARCHIVE_MEMBER_SLACK", "MAX_TAR_HEADER_BYTES", "TarHeaderTooLargeError"]

SCAN_NAME_PATTERN = re.compile(r"^(\d{1,20})\.(png|npy)$", re.ASCII)  # ASCII digits: int() reads others too
#: a scan member's name in an archive: its extension in any case (``.PNG``, as a camera or Windows tool writes it; QA
#: session 40: such scans were left out without a word), extracted under ``SCAN_NAME_PATTERN``'s lower-case name
_ARCHIVE_SCAN_NAME = re.compile(r"^(\d{1,20})\.(png|npy)$", re.ASCII | re.IGNORECASE)
#: A scan's name with a sign (``-1000000.png``): meant as a scan (a sequence folder reads it as time -1 s and
#: refuses it), so refused by name rather than ignored like the other members (see ``extract_scan_archive``).
_SIGNED_SCAN_NAME = re.compile(r"^[+-]\d{1,20}\.(png|npy)$", re.ASCII)

#: Members of other names an archive may hold beyond two per scan (see ``max_archive_members``).
ARCHIVE_MEMBER_SLACK = 1024

_ZIP_DIR_ENTRY = b"PK\x01\x02"  # a central directory entry: 46 bytes + name + extra field + comment
_ZIP64_END = b"PK\x06\x06"  # zip64 end record (56 bytes), followed by its locator (20 bytes)
_ZIP64_END_AND_LOCATOR = 56 + 20
# fields of the end record zipfile._EndRecData returns: signature, directory size, the record's own offset
_ECD_SIGNATURE, _ECD_SIZE, _ECD_LOCATION = 0, 5, 9


#: Largest extended tar header (a PAX header or a GNU long name / link) accepted, bytes. ``tarfile`` reads one
#: whole into memory: a 200 MB PAX header compresses to 30 KB as tar.xz and took +630 MB to refuse (QA, session
#: 21); real ones hold a path and a few times, well under 1 KiB.
MAX_TAR_HEADER_BYTES = 1 << 20


class TarHeaderTooLargeError(tarfile.TarError):
    """An extended tar header larger than ``MAX_TAR_HEADER_BYTES`` (refused before ``tarfile`` reads it)."""


class _BoundedTarInfo(tarfile.TarInfo):
    """``TarInfo`` that refuses an extended header (PAX, GNU long name / link) over ``MAX_TAR_HEADER_BYTES``
    before ``tarfile`` reads it whole (``TarFile(tarinfo=...)`` parses every header through this class)."""

    def _proc_member(self, tarfile_: tarfile.TarFile) -> tarfile.TarInfo:  # type: ignore[override]
        if (self.type in (tarfile.GNUTYPE_LONGNAME, tarfile.GNUTYPE_LONGLINK, tarfile.XHDTYPE, tarfile.XGLTYPE,
                          tarfile.SOLARIS_XHDTYPE) and self.size > MAX_TAR_HEADER_BYTES):
            raise TarHeaderTooLargeError(
                f"a tar member's extended header (PAX or GNU long name) is {self.size:,} bytes; at most "
                f"{MAX_TAR_HEADER_BYTES:,} are accepted")
        return super()._proc_member(tarfile_)  # type: ignore[misc]


def max_archive_members(max_files: int) -> int:
    """Most members of any name (scans, folders, other files, links) a scan archive may hold: two per scan
    (a folder or macOS ``._`` resource file beside each) plus ``ARCHIVE_MEMBER_SLACK``; 41,024 with the default
    ``RERADAR_MAX_ARCHIVE_SCANS`` of 20,000. Without it, 1,000,000 empty tar members (1 MB as tar.xz) took 25 s
    and kept +490 MB of ``TarInfo`` objects resident, though no member was a scan."""
    return 2 * max_files + ARCHIVE_MEMBER_SLACK


def zip_entries_exceed(archive: Path, bound: int) -> bool:
    """True when the zip ``archive``'s central directory lists more than ``bound`` entries; False when it lists
    at most that many or is not a zip ``zipfile`` can read (it then says why itself).

    ``zipfile.ZipFile`` turns the whole central directory into one ``ZipInfo`` per entry when it opens the file,
    and walks the directory's bytes rather than trusting the entry count of the end record, so the entries are
    counted here the same way, over at most ``bound`` + 1 entry headers, where ``zipfile`` finds them: its own
    end-record reader (``zipfile._EndRecData``, the one ``is_zipfile`` uses: zip64 and archive comments as
    zipfile reads them), then the directory right before that record.
    """
    end_record = getattr(zipfile, "_EndRecData", None)
    if end_record is None:  # a future Python without it: zipfile reads the directory unbounded, as before
        return False
    with open(archive, "rb") as f:
        try:
            end = end_record(f)
        except (zipfile.BadZipFile, OSError, struct.error):
            return False
        if not end:
            return False
        size_cd = int(end[_ECD_SIZE])
        start = int(end[_ECD_LOCATION]) - size_cd  # where zipfile.ZipFile reads the directory from
        if end[_ECD_SIGNATURE] == _ZIP64_END:
            start -= _ZIP64_END_AND_LOCATOR
        if start < 0:
            return False
        f.seek(start)
        walked = count = 0
        while walked < size_cd:
            head = f.read(46)
            if len(head) < 46 or head[:4] != _ZIP_DIR_ENTRY:
                return False
            count += 1
            if count > bound:
                return True
            name_len, extra_len, comment_len = struct.unpack_from("<HHH", head, 28)
            f.seek(name_len + extra_len + comment_len, 1)
            walked += 46 + name_len + extra_len + comment_len
    return False


def _member_base(name: str) -> str:
    """An archive member's file name without its folders (``/`` or ``\\`` separated): what it is extracted as."""
    return name.replace("\\", "/").rsplit("/", 1)[-1]


def extract_scan_archive(archive: Path, dest: Path, max_files: int, max_total_bytes: int,
                         max_scan_pixels: int | None = None) -> list[Path]:
    """Extract the scans of ``archive`` into ``dest``; returns the scan paths sorted by timestamp.

    ``max_scan_pixels``: a scan member larger than any scan of that many pixels can be (``max_scan_file_bytes``) is
    refused before it is extracted (None: no such bound).

    Raises:
        BadRequestError: not a zip/tar archive, no scans, two files of one timestamp (compared as numbers:
            ``0160.png``, ``160.png`` and ``160.npy`` are one timestamp), a timestamp (microseconds) above
            ``MAX_SCAN_TIMESTAMP_US`` or with a sign (``-1000000.png``).
        PayloadTooLargeError: more than ``max_files`` scans, more than ``max_archive_members(max_files)``
            members of any name, members (of any name) that expand to more than ``max_total_bytes``, or a scan
            member larger than a scan can be.
        BadRequestError: also a scan-named member that is a link (tar): the build would leave it out.
    """
    max_scan_bytes = None if max_scan_pixels is None else max_scan_file_bytes(max_scan_pixels)

    def check_scan_size(name: str, size: int) -> None:
        if max_scan_bytes is not None and size > max_scan_bytes:
            raise PayloadTooLargeError(
                f"scan archive member {_member_base(name)!r} is {size:,} bytes, more than "
                f"a scan of at most {max_scan_pixels:,} pixels can be ({max_scan_bytes:,} bytes): it holds something "
                "besides the scan; pack the scan files themselves")
    dest.mkdir(parents=True, exist_ok=True)
    written: dict[int, Path] = {}
    packed: dict[int, str] = {}  # each scan's member name in the archive, for messages
    max_members = max_archive_members(max_files)
    members = 0
    total = 0

    def too_many_members() -> PayloadTooLargeError:
        return PayloadTooLargeError(
            f"scan archive holds more than {max_members:,} files and folders (at most two per scan plus "
            f"{ARCHIVE_MEMBER_SLACK:,}, for at most {max_files:,} scans); pack only the scans")

    def count(size: int) -> None:
        """Every member, scan or not: each costs a header parse, and a compressed tar decompresses the data
        of those it skips too."""
        nonlocal members, total
        members += 1
        if members > max_members:
            raise too_many_members()
        total += max(size, 0)
        if total > max_total_bytes:
            raise PayloadTooLargeError(f"scan archive expands to more than {max_total_bytes / 2**20:.0f} MB")

    def accept(name: str) -> tuple[str, int] | None:
        """(file name, timestamp in us) of a scan member, None for any other name."""
        base = _member_base(name)
        match = _ARCHIVE_SCAN_NAME.fullmatch(base)
        if not match:
            if _SIGNED_SCAN_NAME.fullmatch(base):
                raise BadRequestError(f"scan archive member {base!r}: a scan's name must be its timestamp, digits "
                                      f"only (0 to {MAX_SCAN_TIMESTAMP_US} us, no sign); name scan files by their "
                                      f"timestamp in microseconds since the Unix epoch, or remove it from the "
                                      f"archive")
            return None
        stamp = int(match.group(1))
        if stamp > MAX_SCAN_TIMESTAMP_US:
            raise BadRequestError(f"scan archive member {base!r}: timestamp out of range (at most "
                                  f"{MAX_SCAN_TIMESTAMP_US} us); name scan files by their timestamp in "
                                  f"microseconds since the Unix epoch")
        if stamp in written:  # by value: "0160.png" and "160.png" would be two keyframes of one time
            # named as packed (folders too): 'x/y/250000.png' and '250000.png' differ only there
            raise BadRequestError(f"scan archive holds two files with timestamp {stamp} us "
                                  f"({packed[stamp]!r} and {name!r}); keep one scan per timestamp")
        if len(written) + 1 > max_files:
            raise PayloadTooLargeError(f"scan archive holds more than {max_files} scans")
        packed[stamp] = name
        return f"{match.group(1)}.{match.group(2).lower()}", stamp

    with archive.open("rb") as fh:
        head = fh.read(4)
    if not head:
        raise BadRequestError("scan archive is empty (0 bytes); send a .zip, .tar or .tar.gz of the scans")
    if head == b"PK\x03\x04" and not zipfile.is_zipfile(archive):  # QA session 40: "not a .zip" for a cut-off one
        raise BadRequestError("scan archive is a zip that ends early (its central directory is missing: a partial "
                              "download or copy?); send the whole file")
    if zipfile.is_zipfile(archive):
        if zip_entries_exceed(archive, max_members):
            raise too_many_members()
        try:
            with zipfile.ZipFile(archive) as zf:
                for info in zf.infolist():
                    count(info.file_size)
                    if info.is_dir():
                        continue
                    scan = accept(info.filename)
                    if scan is None:
                        continue
                    base, stamp = scan
                    check_scan_size(info.filename, info.file_size)
                    target = dest / base
                    with zf.open(info) as src, open(target, "wb") as dst:
                        shutil.copyfileobj(src, dst, length=1 << 20)
                    written[stamp] = target
        except (zipfile.BadZipFile, OSError, EOFError) as exc:
            raise BadRequestError(f"scan archive is a corrupt zip file ({exc})") from exc
    else:
        try:
            tf = tarfile.open(archive, "r:*", tarinfo=_BoundedTarInfo)  # noqa: SIM115 - closed below
        except TarHeaderTooLargeError as exc:
            raise PayloadTooLargeError(f"scan archive: {exc}") from None
        except (tarfile.TarError, OSError, EOFError):  # tarfile's message lists every compression it tried
            raise BadRequestError("scan archive is not a .zip, .tar or .tar.gz archive") from None
        try:
            with tf:
                while (member := tf.next()) is not None:
                    # TarFile.next() appends every member to tf.members (getmembers() would read them all):
                    # drop them, so memory stays flat however many members there are
                    tf.members.clear()  # type: ignore[attr-defined]  # typeshed does not declare it
                    count(member.size)
                    if not member.isfile():
                        if (member.issym() or member.islnk()) and _ARCHIVE_SCAN_NAME.fullmatch(
                                _member_base(member.name)):
                            raise BadRequestError(  # a link would be left out without a word (QA session 40)
                                f"scan archive member {_member_base(member.name)!r} is a link, not a scan file; "
                                "pack the scan files themselves (tar without links, e.g. tar --dereference)")
                        continue  # devices, folders, links of other names
                    scan = accept(member.name)
                    if scan is None:
                        continue
                    check_scan_size(member.name, member.size)
                    fobj = tf.extractfile(member)
                    if fobj is None:
                        continue
                    base, stamp = scan
                    target = dest / base
                    with fobj, open(target, "wb") as dst:
                        shutil.copyfileobj(fobj, dst, length=1 << 20)
                    written[stamp] = target
        except TarHeaderTooLargeError as exc:
            raise PayloadTooLargeError(f"scan archive: {exc}") from None
        except (tarfile.TarError, OSError, EOFError) as exc:
            detail = " ".join(str(exc).split())  # one line
            raise BadRequestError(f"scan archive is a corrupt or truncated tar(.gz) file ({detail})") from exc
    if not written:
        raise BadRequestError(
            "scan archive holds no scans: expected files named <timestamp_us>.png (Navtech) or <timestamp_us>.npy"
        )
    return [written[stamp] for stamp in sorted(written)]


#: The time a Navtech PNG carries, read from its first row without decoding: the library's reader (this module
#: had its own copy; the name stays for its importers).
navtech_png_scan_time_us = navtech_png_first_time_us

#: Radar preset whose sweep period bounds how far a PNG's file name and embedded time may lie apart when the upload
#: names none (the route takes mid-sweep poses with it too; every preset sweeps at 4 Hz).
SWEEP_PRESET = "boreas"


def pose_file_reader(track: PoseSequence, preset: str | None) -> Callable[[np.ndarray], np.ndarray]:
    """The uploaded pose file's pose at any scan time, for a build's pose-clock check (``datasets.pose_file_reader``
    with the upload's preset, or ``SWEEP_PRESET``: every preset sweeps at 4 Hz): read at the pose file's own rate
    rather than between keyframes (scans 2 s apart cut a corner's turn short enough to hide a 1 s offset)."""
    return datasets_pose_file_reader(track, get_preset(preset or SWEEP_PRESET))


def scan_time_us(path: Path) -> int | None:
    """The time a scan file of an archive gives its keyframe: a Navtech PNG's own (``navtech_png_scan_time_us``;
    None when that cannot be read cheaply), a polar .npy's file name (an array carries no time)."""
    match = SCAN_NAME_PATTERN.fullmatch(path.name)
    if match is None:
        return None
    if match.group(2) == "npy":
        return int(match.group(1))
    return navtech_png_scan_time_us(path)


def check_scan_times(scan_paths: list[Path], preset: str | RadarPreset | None = None,
                     decoded_time_us: Callable[[Path], int | None] | None = None,
                     refusal: Callable[[Path], str | None] | None = None) -> None:
    """Refuse, before the build, two scans of one scan time (``scan_time_us``) and a PNG whose file name and
    embedded time lie more than one sweep of ``preset`` apart (``scan_name_time_message``).

    The map keys its keyframes by the scan time, so two scans of one time would make the built map unreadable;
    file names alone cannot tell (a copy of a PNG under another name carries the original's time). Each
    keyframe's pose is taken from the poses file at its file name's time, so a PNG whose name and embedded time
    are two instants would get the pose of one and the time of the other. A PNG whose first row cannot be read
    cheaply (``scan_time_us`` None) is decoded as the build decodes it (``decoded_time_us``) and checked alike;
    one the decoder refuses, or any when ``decoded_time_us`` is None, is left to the build, which checks every
    scan (``MapRegistry.build_scan_loader``).

    Args:
        scan_paths: the extracted scans (``extract_scan_archive``). preset: the radar preset of the upload (None:
            ``SWEEP_PRESET``); its sweep period is the tolerance. decoded_time_us: the time a scan carries as the
            build decodes it, None when the build refuses it: confirms the first disagreement, since the first
            pixels of an image that is no Navtech scan are no time (the build then says what the file is), and
            times the PNGs the first-row read cannot. refusal: why the build refuses a scan (its message, naming
            the file), None when it reads it: a PNG the first-row read cannot time and the decoder refuses is
            refused here, before the build (QA session 40: a zero-byte last scan failed the build at 90 %).

    Raises:
        BadRequestError: naming both archive members and the time; or the first member whose name and time
            disagree (by its name in the archive), both times, how many disagree and what to do.
    """
    sweep = preset if isinstance(preset, RadarPreset) else get_preset(preset or SWEEP_PRESET)
    seen: dict[int, str] = {}
    off_us: list[int] = []  # name minus embedded time of the PNGs named within a sweep of their time

    def flagged() -> Iterator[Callable[[], str | None]]:
        for path in scan_paths:
            t = scan_time_us(path)
            confirmed = False
            if t is None and decoded_time_us is not None and path.suffix == ".png":
                # a PNG the first-row read cannot time (e.g. Adam7-interlaced, or many chunks before its image
                # data) but the build's decoder may read: its time as the build will take it (these only are
                # decoded here; one the decoder refuses is left to the build, which says why)
                t = decoded_time_us(path)
                confirmed = True
                if t is None and refusal is not None and (why := refusal(path)) is not None:
                    raise ScanFormatError(f"scan archive member {why}")  # 422, as the build's first scan
            if t is None:
                continue
            if t in seen:  # a copy is said to be one (before a name that disagrees with its time, which a copy's does)
                raise BadRequestError(duplicate_scan_time_message(seen[t], path.name, t))
            seen[t] = path.name
            problem = scan_name_time_message(path.name, t, sweep)
            if problem is None:
                name = SCAN_NAME_PATTERN.fullmatch(path.name)
                if name is not None and name.group(2) == "png":
                    off_us.append(int(name.group(1)) - t)
                continue

            def decoded(path: Path = path, problem: str = problem, confirmed: bool = confirmed) -> str | None:
                if decoded_time_us is None or confirmed:
                    return problem
                t_decoded = decoded_time_us(path)
                return None if t_decoded is None else scan_name_time_message(path.name, t_decoded, sweep)

            yield decoded

    first, disagree = first_confirmed_problem(flagged())
    if first is not None:
        more = f" ({disagree} of {len(scan_paths)} scans disagree so; the first is named)" if disagree > 1 else ""
        raise BadRequestError(first + more)
    # as a sequence folder's (load_sequence): a convention, not another instant, but worth a word
    warn_names_off_first_azimuth(off_us, len(scan_paths), sweep, logger, "uploaded scans")


def _scan_layout(path: Path) -> tuple[int, int]:
    """(azimuths, range bins) an archive scan's header declares (a Navtech PNG's columns less its 11 metadata
    columns, an .npy's columns), read from its first 64 kB.

    Raises:
        ScanFormatError: no scan header there (naming the member)."""
    with path.open("rb") as fh:
        head = fh.read(65536)
    try:
        header = scan_header(head, path.stat().st_size)
    except ScanFormatError as exc:
        raise ScanFormatError(f"scan archive member {path.name}: {exc}") from None
    rows, cols = header.shape
    return rows, (cols - NAVTECH_META_COLUMNS if header.format == "png" else cols)


def check_scan_layouts(scan_paths: list[Path], refusal: Callable[[Path], str | None] | None = None) -> None:
    """Refuse, before the build, an archive whose scans are not all of one radar layout, and one whose layout the
    build's decoder refuses (QA session 40: a scan of another radar's range-bin count failed the build only when
    the build reached it, after minutes).

    Reads each scan's header (its first 64 kB: the azimuth and range-bin counts it declares) and decodes one scan
    of the layout as the build will (``refusal``), so the build's own rule and words decide what a layout must be.

    Raises:
        ScanFormatError (422): a member without a scan header; scans of two layouts (naming one of each and how
        many there are of each); the build's reason to refuse the layout's first scan.
    """
    layouts: dict[tuple[int, int], list[str]] = {}
    for path in scan_paths:
        layouts.setdefault(_scan_layout(path), []).append(path.name)
    if len(layouts) > 1:
        (a, a_names), (b, b_names) = sorted(layouts.items(), key=lambda kv: -len(kv[1]))[:2]
        raise ScanFormatError(
            f"the archive holds scans of {len(layouts)} radar layouts: {len(a_names)} of {a[0]} azimuths x {a[1]} "
            f"range bins (e.g. {a_names[0]}) and {len(b_names)} of {b[0]} x {b[1]} (e.g. {b_names[0]}); one map is "
            "built from one radar's scans: send them in separate maps, or convert them (`reradar import-scans`)")
    if refusal is not None and scan_paths and (why := refusal(scan_paths[0])) is not None:
        raise ScanFormatError(f"scan archive member {why}")


def scan_name_time_message(name: str, embedded_us: int, preset: str | RadarPreset | None = None) -> str | None:
    """Why archive member ``name`` (``<timestamp_us>.png``, its name in the archive) cannot be built from when
    the time its name gives and the time it carries (``embedded_us``, its first azimuth's) lie more than one
    sweep of ``preset`` apart: the library's rule and words for a sequence folder (``scan_name_time_mismatch``),
    said of an archive member. None when they agree within a sweep, and for a polar .npy (timed by its name).
    """
    match = SCAN_NAME_PATTERN.fullmatch(name)
    if match is None or match.group(2) != "png":
        return None
    sweep = preset if isinstance(preset, RadarPreset) else get_preset(preset or SWEEP_PRESET)
    problem = scan_name_time_mismatch(name, int(match.group(1)), int(embedded_us), sweep)
    if problem is None:
        return None
    # an archive has no layout to read it in: its scans are named in microseconds
    problem = problem.replace(", or read the folder in the MulRan layout, whose names are nanoseconds",
                              " (an archive's scans are named <timestamp_us>.png)")
    return "scan archive member " + problem.removeprefix("scan ").replace("from the folder", "from the archive")


def duplicate_scan_time_message(first: str, second: str, t_us: int) -> str:
    """What to say of two archive members ``first`` and ``second`` that carry one scan time ``t_us``."""
    both_png = not first.endswith(".npy") and not second.endswith(".npy")
    where = ("the first azimuth timestamp in their Navtech metadata, columns 0-7" if both_png else
             "a Navtech PNG's from its metadata (first azimuth, columns 0-7), a polar .npy's from its file name")
    return (f"scan archive members {first!r} and {second!r} carry the same scan time, {t_us} us ({where}); a map "
            "keeps one keyframe per scan time, so each scan must be its own sweep: remove the copy, or give it its "
            "own time")
