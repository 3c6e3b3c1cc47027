"""``reradar serve``, ``reradar localize --server URL SCAN.png`` and ``reradar demo``."""

from __future__ import annotations

import json
from pathlib import Path

import typer

__all__ = ["register"]


def serve_command(
    host: str = typer.Option("127.0.0.1", help="Address to bind (0.0.0.0 inside containers)."),
    port: int = typer.Option(8080, help="TCP port."),
    maps_dir: Path | None = typer.Option(None, help="Maps folder (default: RERADAR_MAPS_DIR or the cache)."),
    log_level: str = typer.Option("info", help="uvicorn log level."),
) -> None:
    """Run the HTTP service (settings from RERADAR_* environment variables, see docs/SERVICE.md)."""
    import uvicorn

    from service.core.config import Settings
    from service.main import create_app

    overrides = {"maps_dir": maps_dir} if maps_dir is not None else {}
    try:
        settings = Settings(**overrides)  # type: ignore[arg-type]
    except ValueError as exc:
        typer.echo(f"error: invalid settings: {exc}", err=True)
        raise typer.Exit(2) from exc
    uvicorn.run(create_app(settings), host=host, port=port, log_level=log_level)


def localize_command(
    scan: Path = typer.Argument(..., exists=True, dir_okay=False, help="Navtech PNG or .npy scan."),
    server: str = typer.Option("http://127.0.0.1:8080", "--server", help="Service base URL."),
    map_id: str = typer.Option("demo", "--map", help="Map id."),
    top_k: int | None = typer.Option(None, help="Candidates to verify."),
    as_json: bool = typer.Option(False, "--json", help="Print the full JSON response."),
) -> None:
    """Localize one scan with a running service; prints the map-frame pose (metres, degrees)."""
    import logging

    import httpx

    from service.client import ReRadarAPIError, ReRadarClient

    logging.getLogger("httpx").setLevel(logging.WARNING)
    try:
        with ReRadarClient(server) as client:
            res = client.localize(map_id, scan_path=scan, top_k=top_k)
    except ReRadarAPIError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    except httpx.TransportError as exc:
        typer.echo(f"error: cannot reach {server}: {exc}", err=True)
        raise typer.Exit(3) from exc
    if as_json:
        typer.echo(json.dumps(res.model_dump(), indent=2))
    elif res.status == "localized" and res.pose is not None and res.keyframe is not None:
        typer.echo(f"localized: x={res.pose.x_m:.2f} m y={res.pose.y_m:.2f} m yaw={res.pose.yaw_deg:.2f} deg "
                   f"(map {res.map_id}, keyframe {res.keyframe.keyframe_id}, {res.num_inliers} inliers, "
                   f"{res.timings_ms.get('total_ms', 0):.0f} ms)")
    else:
        typer.echo(f"not localized: {res.reason} ({res.num_inliers} inliers)")
    raise typer.Exit(0 if res.status == "localized" else 1)


def demo_command(threads: int = typer.Option(1, min=1, help="torch CPU threads.")) -> None:
    """Serve the shipped demo map on localhost, localize the demo queries over HTTP and print poses + errors."""
    from service.demo import run_demo

    raise typer.Exit(run_demo(echo=typer.echo, threads=threads))


def register(app: typer.Typer) -> None:
    """Add ``serve``, ``localize`` and ``demo`` to the ``reradar`` command line."""
    app.command("serve")(serve_command)
    app.command("localize")(localize_command)
    app.command("demo")(demo_command)
