"""``reradar serve``, ``reradar localize --server URL SCAN.png`` and ``reradar demo``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import typer

if TYPE_CHECKING:  # the server's settings load lazily: the vehicle client needs none of it
    from collections.abc import Callable

    from reradar_core.localization.extractor import FeatureExtractor
    from service.core.config import Settings

__all__ = ["register", "describe_settings_error"]

#: uvicorn's log levels (``--log-level``)
LOG_LEVELS = ("critical", "error", "warning", "info", "debug", "trace")


def _one_of(*choices: str):  # noqa: ANN202 - a typer callback
    """A typer callback accepting only ``choices`` (case-insensitive), as a usage error otherwise."""

    def check(value: str | None) -> str | None:
        if value is not None and value.lower() not in choices:
            raise typer.BadParameter(f"must be one of {', '.join(choices)}; got {value!r}")
        return value.lower() if value is not None else None

    return check


def describe_settings_error(exc: ValueError) -> str:
    """What is wrong with the RERADAR_* settings, one problem per field, without the values given: pydantic's own
    text repeats each input (``input_value=...``), and the values include the operator and vehicle keys."""
    from pydantic import ValidationError

    if not isinstance(exc, ValidationError):
        return str(exc)
    problems = []
    for err in exc.errors(include_url=False, include_input=False, include_context=False):
        loc = "__".join(str(part) for part in err["loc"] if not isinstance(part, int))
        msg = err["msg"].removeprefix("Value error, ")  # a validator's own message names its variables
        problems.append(f"RERADAR_{loc.upper()}: {msg}" if loc else msg)
    return "; ".join(problems)


def settings_or_exit(**overrides: object) -> Settings:
    """``Settings`` from the RERADAR_* environment (and ``overrides``), or exit 2 with one line per bad field
    (``describe_settings_error``: never the values, which hold the keys)."""
    from service.core.config import Settings, unknown_variables

    try:
        settings = Settings(**overrides)  # type: ignore[arg-type]
    except ValueError as exc:
        typer.echo(f"error: invalid settings: {describe_settings_error(exc)}", err=True)
        raise typer.Exit(2) from None
    for var, near in unknown_variables():  # other consumers may read RERADAR_* too: a warning, not a refusal
        typer.echo(f"warning: {var} is not a setting and is ignored" + (f" (did you mean {near}?)" if near else ""),
                   err=True)
    return settings


def check_model_or_exit(settings: Settings) -> None:
    """Exit 2 with one line when ``settings.model`` (RERADAR_MODEL) names no loadable weights: an unknown name, a
    missing file, or a file that does not load (truncated, empty, corrupt, another architecture than its JSON).
    For a process that does not serve the model itself (the supervisor of ``serve --workers N``, whose spawned
    workers load their own): the weights are loaded here in torch (about a second) and dropped. A process that
    serves it loads it once with ``served_model_or_exit`` instead."""
    from reradar_core.errors import ReRadarError
    from reradar_core.model.extractor import DescriptorExtractor
    from reradar_core.model.registry import resolve_weights

    try:
        pt, meta = resolve_weights(settings.model)
        DescriptorExtractor.from_file(pt, meta=meta, runtime="torch", fuse=False)
    except ReRadarError as exc:
        typer.echo(f"error: RERADAR_MODEL: {exc}", err=True)
        raise typer.Exit(2) from None


def served_model_or_exit(settings: Settings,
                         load: Callable[[Settings], FeatureExtractor] | None = None) -> FeatureExtractor:
    """The model this process will serve, loaded by ``load`` (default ``service.main.load_served_extractor``;
    ``reradar worker`` passes ``service.worker.load_build_extractor``), or exit 2 with one line as
    ``check_model_or_exit``: checking the weights and serving them is then one load (about a second) instead
    of two."""
    from reradar_core.errors import ReRadarError

    if load is None:
        from service.main import load_served_extractor

        load = load_served_extractor

    try:
        return load(settings)
    except ReRadarError as exc:
        typer.echo(f"error: RERADAR_MODEL: {exc}", err=True)
        raise typer.Exit(2) from None


def check_redis_credentials_or_exit(settings: Settings, unreachable_exit: int | None = None) -> None:
    """Exit 2 with one line when Redis answers but refuses ``RERADAR_REDIS_URL``'s credentials: a wrong password
    is a setting to fix, not an outage to wait out. An unreachable Redis exits with ``unreachable_exit`` (the
    worker, which needs its queue), or is left to the running service (None), which answers 503
    ``shared_state_unavailable`` until it is back."""
    if not settings.redis_url:
        return
    import redis

    from service.core.shared_state import connect

    try:
        connect(settings.redis_url).ping()
    except (redis.AuthenticationError, redis.exceptions.AuthenticationWrongNumberOfArgsError) as exc:
        typer.echo(f"error: RERADAR_REDIS_URL: Redis refuses its credentials ({exc}); fix the user / password "
                   "in the URL", err=True)
        raise typer.Exit(2) from None
    except redis.RedisError as exc:
        if isinstance(exc, redis.ResponseError) and ("NOAUTH" in str(exc) or "WRONGPASS" in str(exc)):
            typer.echo("error: RERADAR_REDIS_URL: Redis needs a password the URL does not hold (or holds a "
                       "wrong one): redis://:PASSWORD@host:6379/0", err=True)
            raise typer.Exit(2) from None
        if unreachable_exit is not None:  # the URL may hold a password: only what redis says (host and port)
            typer.echo(f"error: cannot reach Redis (RERADAR_REDIS_URL): {exc}", err=True)
            raise typer.Exit(unreachable_exit) from None


def address_free_or_exit(host: str, port: int) -> None:
    """Exit with one line when ``host``:``port`` is in use (another server on the port), binding as uvicorn does
    (IPv6 for a host with ":" and only IPv6, else IPv4; ``SO_REUSEADDR``) and releasing it at once. Any other
    bind problem is left to uvicorn, which names it."""
    import errno
    import socket

    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if family == socket.AF_INET6:
            sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
        try:
            sock.bind((host, port))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                typer.echo(f"error: {host}:{port} is in use (another server runs there: stop it or pick another "
                           "--port)", err=True)
                raise typer.Exit(2) from None


def serve_command(
    host: str = typer.Option("127.0.0.1", help="Address to bind (0.0.0.0 inside containers)."),
    port: int = typer.Option(8080, min=1, max=65535, help="TCP port."),
    maps_dir: Path | None = typer.Option(None, help="Maps folder (default: RERADAR_MAPS_DIR or the cache)."),
    log_level: str = typer.Option("info", callback=_one_of(*LOG_LEVELS),
                                  help=f"uvicorn log level: {', '.join(LOG_LEVELS)}."),
    workers: int = typer.Option(1, min=1, max=64, envvar="RERADAR_WORKERS", help=(
        "Worker processes (uvicorn's supervisor restarts a dead one), each with its own model and maps and 1 "
        "torch / BLAS thread; > 1 needs RERADAR_REDIS_URL (uploaded scans and tracking sessions must be "
        "seen by every worker). One worker per core: docs/OPERATIONS.md.")),
) -> None:
    """Run the HTTP service (settings from RERADAR_* environment variables, see docs/SERVICE.md)."""
    import os

    import uvicorn

    settings = settings_or_exit(**({"maps_dir": maps_dir} if maps_dir is not None else {}))
    # before the model and maps are loaded: a port in use is one line, not a uvicorn log line a minute later
    address_free_or_exit(host, port)
    # before the server starts: a bad setting is one line, not a start-up traceback
    extractor = served_model_or_exit(settings) if workers == 1 else None  # served as loaded: one load
    if extractor is None:  # the spawned workers load their own: this process only checks the weights
        check_model_or_exit(settings)
    check_redis_credentials_or_exit(settings)
    from service.core.http_protocol import HEADER_TIMEOUT_ENV, HeadTimeoutH11Protocol

    HeadTimeoutH11Protocol.header_timeout_s = settings.header_timeout_s
    os.environ[HEADER_TIMEOUT_ENV] = str(settings.header_timeout_s)  # spawned workers read it at import
    if workers == 1:
        from service.main import create_app

        uvicorn.run(create_app(settings, extractor), host=host, port=port, log_level=log_level,
                    http=HeadTimeoutH11Protocol)
        return
    if not settings.redis_url:
        typer.echo(f"error: --workers {workers} needs RERADAR_REDIS_URL: each worker is a separate process, so "
                   "uploaded scans (POST /scans, scan_id) and tracking sessions must live in Redis to be seen by "
                   "every worker (e.g. redis-server on localhost: RERADAR_REDIS_URL=redis://127.0.0.1:6379/0); "
                   "or run one worker per container and scale replicas instead (docs/OPERATIONS.md)", err=True)
        raise typer.Exit(2)
    # the workers are spawned processes that read their settings from the environment, as the first did
    os.environ["RERADAR_MAPS_DIR"] = str(settings.maps_dir)
    # one thread per worker in every pool that reads these before the libraries load (torch's and OpenBLAS'
    # own are also set from RERADAR_TORCH_THREADS / RERADAR_BLAS_THREADS at start-up)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    uvicorn.run("service.main:create_app", factory=True, host=host, port=port, log_level=log_level,
                workers=workers, http=HeadTimeoutH11Protocol)


def localize_command(
    scan: Path | None = typer.Argument(None, dir_okay=False, help="Navtech PNG or .npy scan."),
    server: str = typer.Option("http://127.0.0.1:8080", "--server", help="Service base URL."),
    api_key: str | None = typer.Option(None, "--api-key", envvar="RERADAR_CLIENT_API_KEY", show_envvar=True,
                                       help="Vehicle (or operator) key sent as X-API-Key: needed beyond "
                                            "loopback and whenever the server has vehicle keys. Prefer the "
                                            "variable (a command line is visible to other users)."),
    map_id: str = typer.Option("demo", "--map", help="Map id."),
    top_k: int | None = typer.Option(None, min=1, max=100, help="Candidates retrieved and screened (1-100; the "
                                     "best is verified; default: the server's)."),
    preset: str | None = typer.Option(None, "--preset", help=(
        "Radar preset of the scan (boreas, boreas-2021, oxford, oord, mulran): its range geometry. Default: the "
        "server infers it from the range-bin count; a polar .npy's preset is inferred here, and refused when the "
        "bin count fits several presets (3360: boreas, boreas-2021, mulran). With --follow: the folder's "
        "radar, sent with every scan (default: the folder's own, from its layout or simulator record).")),
    scan_layout: str | None = typer.Option(None, "--scan-layout", callback=_one_of("polar", "navtech"),
                                           help="What an .npy scan holds: polar (A x R power, the default) or "
                                                "navtech (the Navtech PNG's pixels, metadata columns included)."),
    as_json: bool = typer.Option(False, "--json", help="Print the full JSON response."),
    session: str | None = typer.Option(None, "--session", help=(
        "Tracking session id (the server keeps its pose). A single-scan call sends no odometry, so it is always "
        "localized globally and only (re)starts the session; tracking needs odometry between scans: --follow "
        "replays a drive with it, or send odom_* / prior_* fields to POST /localize (docs/SERVICE.md).")),
    follow: Path | None = typer.Option(None, "--follow", file_okay=False, help=(
        "Replay a drive: localize every scan of this sequence folder (Boreas / Oxford / MulRan layout) in order "
        "through one tracking session, print a per-scan table and write a trajectory PNG against the "
        "folder's ground truth. Needs the optional bench extras (dataset reader, matplotlib).")),
    odometry: str = typer.Option("ground-truth", help=(
        "--follow: odometry sent with each scan: `ground-truth` (relative motion between the folder's poses, "
        "with --odometry-noise) or `none` (no odometry: every scan is localized globally, the "
        "session only keeps the last answer).")),
    odometry_noise: float = typer.Option(0.05, min=0.0, help=(
        "--follow: odometry noise, a fraction of each step's length (and of its turn), seeded.")),
    every: int = typer.Option(1, min=1, help="--follow: use every n-th scan."),
    limit: int | None = typer.Option(None, min=1, help="--follow: at most this many scans."),
    no_tracking: bool = typer.Option(False, "--no-tracking", help="--follow: global localization for every scan."),
    out: Path | None = typer.Option(None, "--out", help=(
        "--follow: trajectory PNG, a .png file in an existing folder (default: <folder>-follow.png beside the "
        "folder); an existing folder gets <folder>-follow.png inside it. Checked before the replay starts.")),
    seed: int = typer.Option(0, help="--follow: seed of the odometry noise."),
    timeout: float = typer.Option(60.0, "--timeout", min=0.1, help="Seconds to wait for each answer (a server "
                                  "that accepts the connection but does not answer is reported after it)."),
    time_unit: str | None = typer.Option(None, "--time-unit", callback=_one_of("s", "ms", "us", "ns"), help=(
        "--follow: unit of the folder's pose-file timestamps (s, ms, us, ns) when they are not absolute UTC "
        "times; never guessed (as build-map --time-unit).")),
) -> None:
    """Localize one scan with a running service (or replay a drive with --follow); prints the map-frame pose
    (metres, degrees). Exit status: 0 localized, 1 not localized (--follow: a localized answer off the ground
    truth, a scan answered with an error, or no scan localized at all), 2 an error (bad argument or URL, an error answer, or an answer that is not the ReRadar API's), 3 the
    server cannot be reached, 130 stopped with Ctrl-C (--follow: after the summary and trajectory of the scans
    answered so far; a second Ctrl-C skips them)."""
    import logging

    import httpx

    from service.client import ReRadarAPIError, ReRadarClient

    logging.getLogger("httpx").setLevel(logging.WARNING)
    if (scan is None) == (follow is None):
        typer.echo("error: give one SCAN file or --follow SEQUENCE_DIR", err=True)
        raise typer.Exit(2)
    if time_unit is not None and follow is None:
        typer.echo("error: --time-unit is the unit of a --follow folder's pose times; a single scan carries its "
                   "own time (drop --time-unit, or replay a folder with --follow DIR)", err=True)
        raise typer.Exit(2)
    replay_only = {"--odometry": odometry != "ground-truth", "--odometry-noise": odometry_noise != 0.05,
                   "--every": every != 1, "--limit": limit is not None, "--no-tracking": no_tracking,
                   "--out": out is not None, "--seed": seed != 0}
    given = [name for name, set_ in replay_only.items() if set_]
    if given and follow is None:  # silently ignored, they would suggest a replay that does not happen
        verb, them = ("applies", "it") if len(given) == 1 else ("apply", "them")
        typer.echo(f"error: {', '.join(given)} {verb} to a replay with --follow DIR only; a single SCAN is localized "
                   f"once (drop {them}, or give --follow)", err=True)
        raise typer.Exit(2)
    single_only = {"--json": as_json, "--scan-layout": scan_layout is not None}
    given_single = [name for name, set_ in single_only.items() if set_]
    if given_single and follow is not None:  # they were dropped without a word
        typer.echo(f"error: {', '.join(given_single)} appl{'ies' if len(given_single) == 1 else 'y'} to a single "
                   "SCAN; --follow replays a folder's PNG scans and prints a table and a summary", err=True)
        raise typer.Exit(2)
    if odometry not in ("ground-truth", "none"):
        typer.echo("error: --odometry must be `ground-truth` or `none`", err=True)
        raise typer.Exit(2)
    try:
        client = ReRadarClient(server, api_key=api_key or None, timeout=timeout)
    except ValueError as exc:  # not an http(s) URL with a host, or an unusable key: nothing was sent
        typer.echo(f"error: {'' if str(exc).startswith('invalid API key') else '--server: '}{exc}", err=True)
        raise typer.Exit(2) from None
    try:
        with client:
            if follow is not None:
                from service.follow import follow_sequence

                raise typer.Exit(follow_sequence(client, follow, map_id, echo=typer.echo,
                                                 echo_err=lambda line: typer.echo(line, err=True), top_k=top_k,
                                                 odometry=odometry, odometry_noise=odometry_noise, every=every,
                                                 limit=limit, tracking=not no_tracking, out=out, seed=seed,
                                                 session=session, preset=preset, time_unit=time_unit))
            assert scan is not None
            if not scan.is_file():
                typer.echo(f"error: scan file {scan} does not exist", err=True)
                raise typer.Exit(2)
            if preset is None and scan.suffix.lower() == ".npy" and scan_layout != "navtech":
                preset = _polar_npy_preset(scan)
            res = client.localize(map_id, scan_path=scan, top_k=top_k, session_id=session, preset=preset,
                                  scan_layout=scan_layout)
    except KeyboardInterrupt:  # Ctrl-C: 130 as the shell's convention, not click's "Aborted!" with 1 (not localized);
        # a replay stopped by it has printed its partial summary (follow_sequence); this is a second Ctrl-C there,
        # or one before the replay or during a single scan
        typer.echo("interrupted (Ctrl-C)", err=True)
        raise typer.Exit(130) from None
    except ReRadarAPIError as exc:  # an error status, or (ReRadarResponseError) an answer that is no ReRadar one
        # the server's 401 names its own setting; say what this command takes
        hint = "; give the vehicle key with --api-key or RERADAR_CLIENT_API_KEY" if exc.status_code == 401 else ""
        typer.echo(f"error: {exc}{hint}", err=True)
        raise typer.Exit(2) from None
    except httpx.DecodingError as exc:  # a body its own Content-Encoding does not decode: a bad answer, not an outage
        typer.echo(f"error: the server at {server} answered with a body that cannot be decoded ({exc}): is --server "
                   "the ReRadar API?", err=True)
        raise typer.Exit(2) from None
    except (httpx.InvalidURL, httpx.UnsupportedProtocol) as exc:  # a URL the check above let through: not an outage
        typer.echo(f"error: --server {server!r} is not a usable URL ({exc}); give e.g. http://127.0.0.1:8080",
                   err=True)
        raise typer.Exit(2) from None
    except httpx.TimeoutException as exc:
        typer.echo(f"error: {server} did not answer within {timeout:g} s ({exc}; --timeout)", err=True)
        raise typer.Exit(3) from exc
    except httpx.TransportError as exc:
        typer.echo(f"error: cannot reach {server}: {exc}", err=True)
        raise typer.Exit(3) from exc
    if as_json:
        typer.echo(json.dumps(res.model_dump(), indent=2))
    elif res.status == "localized" and res.pose is not None and res.keyframe is not None:
        unc = res.pose_uncertainty
        sigma = (f" (1 sigma {unc.sigma_x_m:.2f} m / {unc.sigma_y_m:.2f} m / {unc.sigma_yaw_deg:.2f} deg)"
                 if unc is not None else "")
        # a dense answer pairs no landmarks: its evidence is the whole-image correlation's confidence
        how = (f"far view, dense registration, confidence {res.confidence:.2f}" if res.registration == "dense" else
               f"{res.num_inliers} inliers{', far view' if res.view == 'far' else ''}")
        typer.echo(f"localized: x={res.pose.x_m:.2f} m y={res.pose.y_m:.2f} m yaw={res.pose.yaw_deg:.2f} deg{sigma} "
                   f"(map {res.map_id}, keyframe {res.keyframe.keyframe_id}, {how}, {res.mode}, "
                   f"server {res.timings_ms.get('total_ms', 0):.0f} ms)")
    else:
        typer.echo(f"not localized: {res.reason} ({res.num_inliers} inliers, {100 * res.inlier_ratio:.1f} % of "
                   f"the landmarks aligned, confidence {res.confidence:.2f}"
                   f"{'; the far view refused it too' if res.view == 'far' else ''})")
    raise typer.Exit(0 if res.status == "localized" else 1)


def _polar_npy_preset(scan: Path) -> str | None:
    """The preset of a polar .npy scan, from its header's range-bin count (``infer_preset``: refused when
    ambiguous), checked against its shape; the server would otherwise read it with Oxford geometry. None on the
    vehicle-side install (no scan readers there): the server then reads it with the map's preset, as it says."""
    from reradar_core.errors import ScanFormatError

    try:
        from reradar_core.io.scan import check_polar_shape, infer_preset, read_npy_header
    except ModuleNotFoundError:  # `pip install .` (the client) has no OpenCV, which the scan readers import
        typer.echo("note: the polar .npy goes without a preset (this install cannot read scans): the server reads "
                   "it with the map's radar preset; give --preset to name it", err=True)
        return None

    try:
        with scan.open("rb") as fh:
            header = read_npy_header(fh.read(1 << 16), scan.stat().st_size)
        rows, cols = header.shape
        preset = infer_preset(cols, scan.name)
        check_polar_shape(rows, cols, preset, scan.name)
    except (OSError, ScanFormatError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    return preset.name


def demo_command(threads: int = typer.Option(1, min=1, help="torch CPU threads.")) -> None:
    """Serve the shipped demo map on localhost, localize the demo queries over HTTP and print poses + errors."""
    from service.demo import run_demo

    raise typer.Exit(run_demo(echo=typer.echo, threads=threads))


def register(app: typer.Typer) -> None:
    """Add ``serve``, ``localize`` and ``demo`` to the ``reradar`` command line."""
    app.command("serve")(serve_command)
    app.command("localize")(localize_command)
    app.command("demo")(demo_command)
