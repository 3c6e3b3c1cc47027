"""The ``reradar`` command line: one entry point, each sub-command imported only when it runs.

The library (``reradar_core``), the map store (``maps``) and the service (``service``) each define their
sub-commands next to the code they drive (a ``register(app)`` function per module); this package only wires
them, so ``reradar_core`` never imports ``maps`` or ``service``. Sub-command modules (and torch, FAISS,
e2cnn behind them) are imported lazily: ``reradar --help`` and the vehicle-side ``reradar localize`` start in
well under a second and work in a client-only install (``pip install reradar``, no torch).
"""

from reradar_cli.main import COMMANDS, app, main

__all__ = ["COMMANDS", "app", "main"]
