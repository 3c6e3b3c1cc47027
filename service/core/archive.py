"""Safe extraction of uploaded scan archives (zip / tar / tar.gz) for map building.

Only regular files named ``<timestamp_us>.png`` or ``<timestamp_us>.npy`` are extracted, flattened into one
folder (directory parts are dropped, so ``../`` tricks cannot escape); links, devices and other files are
ignored; total size and file count are bounded before anything is written.
"""

from __future__ import annotations

import re
import shutil
import tarfile
import zipfile
from pathlib import Path

from service.core.errors import BadRequestError, PayloadTooLargeError

__all__ = ["extract_scan_archive", "SCAN_NAME_PATTERN", "MAX_SCAN_TIMESTAMP_US"]

SCAN_NAME_PATTERN = re.compile(r"^(\d{1,20})\.(png|npy)$")
#: Largest timestamp a scan file may be named with, microseconds since the Unix epoch (2**62, year ~148,000):
#: far beyond any real time, and small enough that the int64 arithmetic on timestamps (mid-sweep offsets,
#: time-span checks) cannot overflow.
MAX_SCAN_TIMESTAMP_US = 2**62


def _members_zip(zf: zipfile.ZipFile) -> list[tuple[str, int, zipfile.ZipInfo]]:
    out = []
    for info in zf.infolist():
        if info.is_dir():
            continue
        out.append((info.filename, info.file_size, info))
    return out


def extract_scan_archive(archive: Path, dest: Path, max_files: int, max_total_bytes: int) -> list[Path]:
    """Extract the scans of ``archive`` into ``dest``; returns the scan paths sorted by timestamp.

    Raises:
        BadRequestError: not a zip/tar archive, no scans, duplicate timestamps, a timestamp (microseconds)
            above ``MAX_SCAN_TIMESTAMP_US``.
        PayloadTooLargeError: more than ``max_files`` scans or more than ``max_total_bytes`` uncompressed.
    """
    dest.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    total = 0

    def accept(name: str, size: int) -> str | None:
        nonlocal total
        base = name.replace("\\", "/").rsplit("/", 1)[-1]
        match = SCAN_NAME_PATTERN.match(base)
        if not match:
            return None
        if int(match.group(1)) > MAX_SCAN_TIMESTAMP_US:
            raise BadRequestError(f"scan archive member {base!r}: timestamp out of range (at most "
                                  f"{MAX_SCAN_TIMESTAMP_US} us); name scan files by their timestamp in "
                                  f"microseconds since the Unix epoch")
        if base in written:
            raise BadRequestError(f"scan archive holds two files named {base!r}")
        total += size
        if total > max_total_bytes:
            raise PayloadTooLargeError(f"scan archive expands to more than {max_total_bytes / 2**20:.0f} MB")
        if len(written) + 1 > max_files:
            raise PayloadTooLargeError(f"scan archive holds more than {max_files} scans")
        return base

    if zipfile.is_zipfile(archive):
        try:
            with zipfile.ZipFile(archive) as zf:
                for name, size, info in _members_zip(zf):
                    base = accept(name, size)
                    if base is None:
                        continue
                    target = dest / base
                    with zf.open(info) as src, open(target, "wb") as dst:
                        shutil.copyfileobj(src, dst, length=1 << 20)
                    written[base] = target
        except (zipfile.BadZipFile, OSError, EOFError) as exc:
            raise BadRequestError(f"scan archive is a corrupt zip file ({exc})") from exc
    else:
        try:
            tf = tarfile.open(archive, "r:*")  # noqa: SIM115 - closed below
        except (tarfile.TarError, OSError, EOFError):  # tarfile's message lists every compression it tried
            raise BadRequestError("scan archive is not a .zip, .tar or .tar.gz archive") from None
        try:
            with tf:
                for member in tf:
                    if not member.isfile():
                        continue  # links, devices, folders
                    base = accept(member.name, member.size)
                    if base is None:
                        continue
                    fobj = tf.extractfile(member)
                    if fobj is None:
                        continue
                    target = dest / base
                    with fobj, open(target, "wb") as dst:
                        shutil.copyfileobj(fobj, dst, length=1 << 20)
                    written[base] = target
        except (tarfile.TarError, OSError, EOFError) as exc:
            detail = " ".join(str(exc).split())  # one line
            raise BadRequestError(f"scan archive is a corrupt or truncated tar(.gz) file ({detail})") from exc
    if not written:
        raise BadRequestError(
            "scan archive holds no scans: expected files named <timestamp_us>.png (Navtech) or <timestamp_us>.npy"
        )
    return sorted(written.values(), key=lambda p: int(SCAN_NAME_PATTERN.match(p.name).group(1)))  # type: ignore[union-attr]
