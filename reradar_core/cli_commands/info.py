"""``reradar info``: print a scan's metadata and statistics."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from reradar_core.errors import ReRadarError
from reradar_core.io.scan import load_scan


def register(app: typer.Typer) -> None:
    @app.command("info")
    def info(
        scan: Path = typer.Argument(..., help="Navtech polar PNG or .npy scan."),
        preset: str = typer.Option(None, help="Radar preset (boreas, boreas-2021, oxford, oord, mulran). Inferred "
                                   "from the range-bin count when that names one range geometry (3768: oxford); "
                                   "needed for 3360 bins (boreas, boreas-2021 and mulran differ)."),
        scan_layout: str = typer.Option("polar", "--scan-layout", help="What an .npy scan holds: polar (A x R "
                                        "power, the default) or navtech (the Navtech PNG's pixels, metadata "
                                        "columns included; as `reradar localize --scan-layout`)."),
    ) -> None:
        """Print a scan's shape, timing and power statistics."""
        if scan.is_dir():
            typer.echo(f"error: {scan}: is a folder; pass one scan file (.png or .npy)", err=True)
            raise typer.Exit(2)
        layout = scan_layout.lower()
        if layout not in ("polar", "navtech"):
            typer.echo(f"error: --scan-layout must be polar or navtech; got {scan_layout!r}", err=True)
            raise typer.Exit(2)
        try:
            s = load_scan(scan, preset, npy_layout=layout)  # type: ignore[arg-type]  # checked above
        except ReRadarError as exc:
            msg = str(exc)  # every message names the file (some checks of the decoded power do not)
            typer.echo(f"error: {msg if str(scan) in msg or scan.name in msg else f'{scan}: {msg}'}", err=True)
            raise typer.Exit(2) from exc
        sweep_ms = (s.timestamps_us[-1] - s.timestamps_us[0]) / 1000.0
        typer.echo(f"file: {scan}")
        typer.echo(f"preset: {s.preset}  azimuths: {s.num_azimuths}  range bins: {s.num_range_bins} "
                   f"x {s.range_resolution_m} m (max {s.ranges_m[-1]:.1f} m)")
        typer.echo(f"timestamp: {s.timestamp_us} us  sweep: {sweep_ms:.1f} ms  valid azimuths: {int(s.valid.sum())}")
        typer.echo(f"power: mean {s.power.mean():.4f}  p99 {np.percentile(s.power, 99):.4f} (fraction of full scale)")
