"""The ``reradar`` command line: one entry point for everything a user runs.

Sub-commands register themselves from their stage modules (``sim``, ``train``, ``build-map``, ``localize``,
``bench``, ``serve``); each lives next to the code it drives so this file only wires them.
"""

from __future__ import annotations

import importlib
import logging

import typer

app = typer.Typer(
    name="reradar",
    help="ReRadar: radar global localization (place recognition + 3-DoF pose) from one Navtech scan.",
    no_args_is_help=True,
    add_completion=False,
)

# Modules that add commands to ``app`` via ``register(app)``; missing ones are skipped so a partial install
# still gives a working CLI.
_COMMAND_MODULES = (
    "reradar_core.cli_commands.info",
    "reradar_core.sim.cli",
    "reradar_core.training.cli",
    "maps.cli",
    "reradar_core.benchmark.cli",
    "service.cli",
    "service.worker",
)


@app.callback()
def _main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Log debug messages.")) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")


for _mod in _COMMAND_MODULES:
    try:
        module = importlib.import_module(_mod)
    except ModuleNotFoundError as exc:  # only skip modules not yet present, never hide real import bugs
        if exc.name is None or not _mod.startswith(exc.name):
            raise
        continue
    module.register(app)

if __name__ == "__main__":  # pragma: no cover
    app()
