"""``reradar import-scans``: convert polar scans of another layout or resolution into Navtech PNGs."""

from __future__ import annotations

import math
import re
from pathlib import Path

import typer

from reradar_core.errors import ReRadarError


def register(app: typer.Typer) -> None:
    @app.command("import-scans")
    def import_scans(
        sources: list[Path] = typer.Argument(..., help="Foreign polar scans: greyscale PNG (no metadata) or .npy."),
        out: Path = typer.Option(..., "--out", help="Folder for the Navtech PNGs (created)."),
        range_resolution: float = typer.Option(..., "--range-resolution",
                                               help="Metres per range bin of the SOURCE scans (e.g. 0.175)."),
        preset: str = typer.Option("boreas", help="Target radar preset (boreas, oxford, oord, mulran)."),
        range_offset: float = typer.Option(0.0, "--range-offset", help="Range of the source's bin 0, metres."),
        transposed: bool = typer.Option(False, "--transposed",
                                        help="Source rows are range bins and columns azimuths."),
        start_azimuth_deg: float = typer.Option(0.0, "--start-azimuth-deg",
                                                help="Azimuth of the first source beam, degrees clockwise."),
    ) -> None:
        """Resample foreign polar scans onto a preset's range grid and write them as Navtech PNGs.

        Output names are the source names when they are microsecond timestamps, else 1, 2, 3, ... seconds apart
        in microseconds from 0 (give sequences timestamped names to keep their timing). Read them back with
        `reradar info`, `build-map --dataset`, `localize`.
        """
        import cv2
        import numpy as np

        from reradar_core.io.importer import ForeignScanLayout, import_polar_scan
        from reradar_core.io.scan import write_navtech_png

        try:
            layout = ForeignScanLayout(range_resolution, range_offset, 1 if transposed else 0,
                                       math.radians(start_azimuth_deg))
            out.mkdir(parents=True, exist_ok=True)
            for k, src in enumerate(sorted(sources)):
                if src.suffix.lower() == ".npy":
                    array = np.load(src, allow_pickle=False)
                else:
                    array = cv2.imread(str(src), cv2.IMREAD_GRAYSCALE)
                    if array is None:
                        raise ReRadarError(f"{src.name}: not a readable image")
                stamp = int(src.stem) if re.fullmatch(r"\d{10,}", src.stem) else (k + 1) * 1_000_000
                scan = import_polar_scan(array, layout, preset, start_time_us=stamp)
                write_navtech_png(scan, out / f"{stamp}.png")
        except (ReRadarError, OSError, ValueError) as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(2) from exc
        typer.echo(f"wrote {len(sources)} Navtech PNG(s) for preset {preset!r} to {out}")
