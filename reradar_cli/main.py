"""The ``reradar`` app: a Typer group whose sub-commands are imported on first use (``COMMANDS``)."""

from __future__ import annotations

import functools
import importlib
import logging
import os
import sys
from collections.abc import Callable
from typing import Any

import typer
import typer.core

__all__ = ["COMMANDS", "app", "main"]

#: sub-command -> (module whose ``register(app)`` defines it, one-line help shown by ``reradar --help``).
#: The help text is repeated here so listing the commands imports none of them.
COMMANDS: dict[str, tuple[str, str]] = {
    "info": ("reradar_core.cli_commands.info", "Print a scan's shape, timing and power statistics."),
    "cache": ("reradar_core.cli_commands.cache", "List the cache folder's parts and sizes; --prune removes stale ones."),
    "fit-confidence": ("reradar_core.cli_commands.fit_confidence", "Fit the calibrated answer confidence on training splits."),
    "export-onnx": ("reradar_core.cli_commands.export_onnx",
                    "Write each model's network as an ONNX graph beside its weights (faster inference)."),
    "import-scans": ("reradar_core.cli_commands.import_scans",
                     "Convert polar scans of another layout or resolution into Navtech PNGs of a preset."),
    "sim": ("reradar_core.sim.cli", "Render a simulated radar sequence along a trajectory, in a real dataset layout."),
    "sim-suite": ("reradar_core.sim.cli", "Render a named benchmark suite or training split."),
    "sim-report": ("reradar_core.sim.cli", "Print real vs simulated scan statistics side by side."),
    "train": ("reradar_core.training.cli", "Train the descriptor network with InfoNCE and save weights."),
    "build-map": ("maps.cli", "Build a keyframe map (global + local descriptors, poses) from a radar sequence."),
    "map-info": ("maps.cli", "Print a map's metadata as JSON."),
    "map-repetition": ("maps.cli", "Measure where a map repeats itself and store it in the map (older maps)."),
    "bench": ("reradar_core.benchmark.cli", "Benchmark ReRadar against RingKey, RaPlace, RadVLAD, "
              "ResNet18-NetVLAD and ReFeree."),
    "serve": ("service.cli", "Run the HTTP service (settings from RERADAR_* environment variables)."),
    "localize": ("service.cli", "Localize one scan (or replay a drive with --follow) with a running service."),
    "demo": ("service.cli", "Serve the demo map on localhost, localize the demo queries over HTTP, print errors."),
    "worker": ("service.worker", "Run a map-build worker: queued builds from Redis (needs RERADAR_REDIS_URL)."),
}


#: top-level modules of the optional extras (``server``, ``plot``, ...): missing ones get an install hint
OPTIONAL_MODULES = frozenset({"torch", "e2cnn", "faiss", "cv2", "scipy", "h5py", "fastapi", "uvicorn", "starlette",
                              "pydantic_settings", "multipart", "python_multipart", "tqdm", "matplotlib", "onnx",
                              "onnxscript", "onnxruntime"})


def _missing_extra(name: str, exc: ModuleNotFoundError) -> typer.Exit:
    typer.echo(f"error: 'reradar {name}' needs the optional dependency {exc.name!r}, which is not installed; "
               "install the extras, e.g. pip install 'reradar[server]' or 'reradar[all]' (see README)", err=True)
    return typer.Exit(2)


def _guarded(name: str, callback: Callable[..., Any]) -> Callable[..., Any]:
    """``callback`` turning a missing optional dependency (imported lazily inside a command) into an
    actionable error instead of a traceback, and so an unreadable or unwritable file (an ``OSError``) that the
    command did not check itself."""

    @functools.wraps(callback)
    def run(*args: Any, **kwargs: Any) -> Any:
        try:
            return callback(*args, **kwargs)
        except ModuleNotFoundError as exc:
            if (exc.name or "").split(".")[0] not in OPTIONAL_MODULES:
                raise
            raise _missing_extra(name, exc) from exc
        except BrokenPipeError:  # the reader of stdout went away (`reradar ... | head`): stop quietly, as cat does
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at the final flush
            raise typer.Exit(141) from None
        except OSError as exc:  # a file the user named cannot be read or written: one line, not a traceback
            where = f": {exc.filename}" if exc.filename else ""
            typer.echo(f"error: {exc.strerror or exc}{where}", err=True)
            raise typer.Exit(2) from None

    return run


def load_command(name: str) -> Any:
    """Import the module that defines sub-command ``name`` and return it as a (Typer's) click command; exits
    with status 2 and an actionable message when the module needs an optional dependency that is missing."""
    module_name, _ = COMMANDS[name]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:  # a client-only install lacks the server/training/bench extras
        raise _missing_extra(name, exc) from exc
    sub = typer.Typer()
    module.register(sub)
    group = typer.main.get_group(sub)
    cmd = group.get_command(typer.Context(group), name)
    if cmd is None:  # pragma: no cover - COMMANDS and the modules disagree
        raise RuntimeError(f"module {module_name} does not define the command {name!r}")
    if cmd.callback is not None:
        cmd.callback = _guarded(name, cmd.callback)
    return cmd


_option_type_label = typer.core.TyperOption.display_type_rich


def _flag_without_type_label(self: typer.core.TyperOption, ctx: Any) -> str | None:
    """typer 0.29 labels an on/off flag ``<bool>`` in ``--help``, which reads as an option taking a value
    (``--json true`` is then refused); a flag shows no type, as click's own help does."""
    return None if self.is_flag else _option_type_label(self, ctx)


typer.core.TyperOption.display_type_rich = _flag_without_type_label  # type: ignore[method-assign]


class LazyGroup(typer.core.TyperGroup):
    """Lists ``COMMANDS`` from their static help; imports a command's module only to run it (or show its
    own ``--help``)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._resolving = False

    def list_commands(self, ctx: Any) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: Any, cmd_name: str) -> Any:
        if cmd_name not in COMMANDS:
            return None
        if self._resolving:
            return load_command(cmd_name)
        # a placeholder that only carries the help line (listing the commands imports none of them)
        return typer.core.TyperCommand(cmd_name, help=COMMANDS[cmd_name][1], short_help=COMMANDS[cmd_name][1])

    def resolve_command(self, ctx: Any, args: list[str]) -> Any:
        self._resolving = True
        try:
            return super().resolve_command(ctx, args)
        finally:
            self._resolving = False


app = typer.Typer(
    name="reradar",
    cls=LazyGroup,
    help="ReRadar: radar global localization (place recognition + 3-DoF pose) from one Navtech scan.",
    no_args_is_help=True,
    add_completion=False,
)


@app.callback()
def _main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Log debug messages.")) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not verbose:  # faiss logs each CPU-specific build it does not find ("No module named ...avx512") at INFO
        logging.getLogger("faiss.loader").setLevel(logging.WARNING)


def main() -> None:
    """Console-script entry point (``reradar``)."""
    app()
