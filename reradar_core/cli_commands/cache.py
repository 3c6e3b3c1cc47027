"""``reradar cache``: what the cache folder holds, and removing what no run will read again.

The cache (``$RERADAR_CACHE_DIR``, default ``./.cache/reradar``; ``reradar_core.paths.cache_dir``) grows without
bound otherwise: every simulator version renders its suites into its own ``sim/v<N>`` folder (7-9 GB for all suites
and training splits) and never reads another version's, and ``benchmarks/calibrate_sim.py`` keeps every probe's
renders (0.3-1.3 GB each). A full disk stops every run on the machine, so this lists each part with its size and
whether anything still reads it, and ``--prune`` removes the parts nothing reads:

- ``sim/v<N>`` for N other than the current ``SIM_VERSION`` (stale: renders are never reused across versions; other
  folders under ``sim/`` are not version folders and are kept), when it holds a simulator render (a
  ``.reradar_render_version`` marker within four levels) and no loose files of its own;
- ``calib/`` (probe renders, re-rendered on demand by ``benchmarks/calibrate_sim.py``), when it holds nothing but
  the probe's ``<suite>-<16 hex digits>.npz`` files.

A folder judged by its name alone is never removed: ``RERADAR_CACHE_DIR`` set to a project or home folder by
mistake must not lose that folder's own ``calib/`` or ``sim/v3/``.
- training images (``training/cartesian/<key>``) and benchmark feature caches (``bench/features/<method>/<seq>.h5``)
  derived from a sequence folder that no longer exists (each records its folder since session 17:
  ``paths.CACHE_SOURCE_FILE`` / ``CACHE_SOURCE_ATTR``; older entries record none and are kept).

Everything else (the current renders, training images, benchmark feature caches and results, confidence runs, the
service's maps when ``RERADAR_MAPS_DIR`` is left at its default ``$RERADAR_CACHE_DIR/maps``) is listed and kept.
Sizes are disk usage with hard links counted once (``verify_sim_identity --carry-over`` links a version's renders
into the next), and what a prune frees counts only files no kept part links to.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import stat
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import typer

from reradar_core.errors import ReRadarError
from reradar_core.paths import CACHE_SOURCE_ATTR, CACHE_SOURCE_FILE, cache_dir
from reradar_core.sim.writer import SIM_VERSION

__all__ = ["CachePart", "cache_parts", "prune_parts", "reclaimable_bytes", "register", "source_of"]


@dataclass(frozen=True)
class CachePart:
    """One part of the cache folder.

    Attributes:
        paths: its folders.
        what: what it holds, in words.
        size_bytes: disk usage of its files (hard links within the part counted once).
        stale: True when no run reads it again (``--prune`` removes it).
        why: the reason, for the listing.
        inodes: its files, as ``_inodes`` gives them (walked once: sizes and what a prune frees both come from it).
    """

    paths: tuple[Path, ...]
    what: str
    size_bytes: int
    stale: bool
    why: str
    inodes: dict[tuple[int, int], tuple[int, int, int]] = field(default_factory=dict, repr=False, compare=False)


def _inodes(path: Path) -> dict[tuple[int, int], tuple[int, int, int]]:
    """{(device, inode): (disk bytes, link count, links under ``path``)} of every regular file at or under
    ``path`` (a folder or one file)."""
    files = [str(path)] if path.is_file() else (os.path.join(d, f) for d, _dirs, fs in os.walk(path) for f in fs)
    out: dict[tuple[int, int], tuple[int, int, int]] = {}
    for f in files:
        try:
            st = os.lstat(f)
        except OSError:  # removed while we walk
            continue
        if stat.S_ISREG(st.st_mode):
            key = (st.st_dev, st.st_ino)
            seen = out[key][2] if key in out else 0
            out[key] = (st.st_blocks * 512, st.st_nlink, seen + 1)
    return out


def source_of(entry: Path) -> str | None:
    """The input folder a derived cache entry records (``CACHE_SOURCE_FILE`` in a folder, ``CACHE_SOURCE_ATTR`` in an
    HDF5 file), or None when it records none (written before session 17) or cannot be read now (in use)."""
    try:
        if entry.is_dir():
            record = entry / CACHE_SOURCE_FILE
            return str(json.loads(record.read_text())["root"]) if record.is_file() else None
        if entry.suffix == ".h5":
            import h5py  # the benchmark's feature files

            with h5py.File(entry, "r") as f:
                value = f.attrs.get(CACHE_SOURCE_ATTR)
            return None if value is None else str(value)
    except (OSError, ValueError, KeyError, TypeError):  # locked by a running benchmark, or unreadable
        return None
    return None


def _derived(entries: list[Path], what: str) -> Iterable[tuple[tuple[Path, ...], str, bool, str]]:
    """Parts of derived cache ``entries``: those whose recorded source folder is gone (stale), and the rest."""
    gone, unknown, live = [], [], []
    for e in entries:
        src = source_of(e)
        (unknown if src is None else live if Path(src).exists() else gone).append(e)
    if gone:
        yield tuple(gone), f"{what} of folders that no longer exist ({len(gone)})", True, "never read: their source is gone"
    if live or unknown:
        why = "kept" + (f" ({len(unknown)} written before sources were recorded)" if unknown else "")
        yield tuple(live + unknown), f"{what} ({len(live) + len(unknown)})", False, why


#: kept parts with a name of their own (the rest of ``bench/`` is listed as one part: run results)
_KEPT = {("training", "runs"): "training runs", ("bench", "service"): "service benchmark maps",
         ("confidence",): "confidence-fit runs", ("maps",): "the service's registered maps (RERADAR_MAPS_DIR default)"}
#: derived caches, judged entry by entry by the source folder each records
_DERIVED = {("training", "cartesian"): "training images (Cartesian crops)", ("bench", "features"): "benchmark feature caches"}


#: the render marker the simulator writes into every sequence folder (``sim.writer``)
_RENDER_MARKER = ".reradar_render_version"
_CALIB_FILE = re.compile(r"[a-z0-9][a-z0-9_-]*-[0-9a-f]{16}\.npz")


def _holds_renders(version_dir: Path, depth: int = 4) -> bool:
    """True when ``version_dir`` (``sim/v<N>``) holds at least one simulator render (the marker within ``depth``
    levels) and no loose files of its own: what the simulator writes there, not a folder that shares the name."""
    if any(e.is_file() or e.is_symlink() for e in version_dir.iterdir()):
        return False
    level = [version_dir]
    for _ in range(depth):
        if any((d / _RENDER_MARKER).is_file() for d in level):
            return True
        level = [e for d in level for e in d.iterdir() if e.is_dir() and not e.is_symlink()]
    return False


def _holds_calib_renders(calib: Path) -> bool:
    """True when ``calib/`` holds only ``benchmarks/calibrate_sim.py``'s ``<suite>-<tag>.npz`` files."""
    return all(e.is_file() and not e.is_symlink() and _CALIB_FILE.fullmatch(e.name) for e in calib.iterdir())


def _parts(root: Path) -> Iterable[tuple[tuple[Path, ...], str, bool, str]]:
    """(folders, what, stale, why) of every part of the cache under ``root``."""
    sim = root / "sim"
    if sim.is_dir():
        for d in sorted((d for d in sim.iterdir() if d.is_dir()), key=lambda p: (len(p.name), p.name)):
            version = d.name[1:]
            if not re.fullmatch(r"v\d+", d.name):  # not a version folder: someone's own renders, never pruned
                yield (d,), f"sim/{d.name}", False, "kept (not a simulator version folder sim/v<N>)"
            elif version == SIM_VERSION:
                yield (d,), f"simulator v{version} renders", False, "current simulator version"
            elif not _holds_renders(d):
                yield (d,), f"sim/{d.name}", False, "kept (holds no simulator render, or files of its own)"
            else:
                yield (d,), f"simulator v{version} renders", True, f"never read: renders are per version (now v{SIM_VERSION})"
    if (root / "calib").is_dir():
        if _holds_calib_renders(root / "calib"):
            yield (root / "calib",), "calibration probe renders", True, "re-rendered on demand by benchmarks/calibrate_sim.py"
        else:
            yield (root / "calib",), "calib", False, "kept (holds files that are not calibration probe renders)"
    named = {root.joinpath(*k): what for k, what in _KEPT.items()}
    for path, what in named.items():
        if path.is_dir():
            yield (path,), what, False, "kept"
    derived = {root.joinpath(*k): what for k, what in _DERIVED.items()}
    for path, what in derived.items():
        if path.is_dir():
            entries = ([e for e in sorted(path.iterdir()) if e.is_dir()] if path.name == "cartesian"
                       else sorted(path.glob("*/*.h5")))
            yield from _derived(entries, what)
    named.update(derived)
    rest = [d for top in ("bench", "training") if (root / top).is_dir()
            for d in sorted((root / top).iterdir()) if d.is_dir() and d not in named]
    if rest:
        yield tuple(rest), f"benchmark and training results ({len(rest)} folders)", False, "kept"
    known = {"sim", "calib", "bench", "training", "confidence", "maps"}
    for d in sorted(root.iterdir()):
        if d.is_dir() and d.name not in known:
            yield (d,), d.name, False, "kept (not written by ReRadar's own runs)"


def cache_parts(root: Path) -> list[CachePart]:
    """Every part of the cache folder ``root`` with its size and whether it is stale (see the module docstring)."""
    out = []
    for paths, what, stale, why in _parts(root):
        inodes: dict[tuple[int, int], tuple[int, int, int]] = {}
        for p in paths:
            for key, (size, nlink, seen) in _inodes(p).items():
                inodes[key] = (size, nlink, seen + (inodes[key][2] if key in inodes else 0))
        out.append(CachePart(paths, what, sum(b for b, _, _ in inodes.values()), stale, why, inodes))
    return out


def reclaimable_bytes(parts: list[CachePart]) -> int:
    """Bytes a prune of the stale ``parts`` frees: the files all of whose hard links lie in stale parts."""
    links: dict[tuple[int, int], list[int]] = {}
    for p in parts:
        if p.stale:
            for key, (size, nlink, seen) in p.inodes.items():
                links.setdefault(key, [size, nlink, 0])[2] += seen
    return sum(size for size, nlink, seen in links.values() if seen >= nlink)


def prune_parts(parts: list[CachePart]) -> list[Path]:
    """Remove the stale ``parts``' folders and files; returns what was removed."""
    removed = []
    for p in parts:
        for path in p.paths if p.stale else ():
            if path.is_dir():
                shutil.rmtree(path)
            elif path.is_file():
                path.unlink()
            else:
                continue
            removed.append(path)
    return removed


def _gb(n: int) -> str:
    return f"{n / 1e9:.2f} GB" if n >= 1e7 else f"{n / 1e6:.1f} MB"


def register(app: typer.Typer) -> None:
    @app.command("cache")
    def cache(
        prune: bool = typer.Option(False, "--prune", help="Remove the stale parts: old simulator versions' renders "
                                   "(sim/v<N>), calibration probe renders, and training images and benchmark "
                                   "feature caches whose source folder no longer exists."),
    ) -> None:
        """List the cache folder's parts with their sizes; --prune removes what no run reads again."""
        try:
            root = cache_dir()
        except ReRadarError as exc:  # RERADAR_CACHE_DIR names a file, or a folder that cannot be created
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from None
        parts = cache_parts(root)
        free = shutil.disk_usage(root).free
        typer.echo(f"cache {root} ({_gb(free)} free on its disk; simulator v{SIM_VERSION})")
        typer.echo("| part | size | status |")
        typer.echo("|---|---|---|")
        for p in parts:
            typer.echo(f"| {p.what} | {_gb(p.size_bytes)} | {'stale: ' if p.stale else ''}{p.why} |")
        if not any(p.stale for p in parts):
            typer.echo("nothing stale")
            return
        reclaim = reclaimable_bytes(parts)
        if not prune:
            typer.echo(f"stale parts hold {_gb(reclaim)}: `reradar cache --prune` removes them")
            return
        removed = prune_parts(parts)
        after = shutil.disk_usage(root).free
        typer.echo(f"removed {len(removed)} stale folder(s) / file(s); {_gb(max(after - free, 0))} freed on the disk")
