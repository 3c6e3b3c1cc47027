"""One log format for the service, the worker and uvicorn: JSON lines on stderr (stdlib ``logging`` only).

Each line is one JSON object: ``ts`` (UTC, ISO 8601, milliseconds), ``level``, ``logger``, ``msg``, ``exc``
(traceback, when any) and any ``extra={...}`` fields the caller gave. uvicorn's access lines also carry
``client``, ``method``, ``path`` and ``status``. ``RERADAR_LOG_FORMAT=text`` gives one human-readable line
instead (same fields).

Importing this module silences faiss' loader, which logs a ``ModuleNotFoundError`` at INFO on every start
while probing for optional AVX-512 builds: it must run before faiss is first imported.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import sys
from typing import Any, Literal

__all__ = ["JsonFormatter", "configure_logging", "quiet_noisy_loggers"]

#: Attributes every ``LogRecord`` has; anything else on a record came from ``extra=`` and is logged.
_STANDARD_ATTRS = frozenset(vars(logging.LogRecord("", 0, "", 0, "", (), None))) | {"message", "asctime", "taskName",
                                                                                    # uvicorn's terminal-coloured copy of msg
                                                                                    "color_message"}

#: Loggers that own handlers of their own and must go through ours instead.
_FOREIGN_LOGGERS = ("uvicorn", "uvicorn.error", "uvicorn.access", "arq", "arq.worker", "arq.jobs")


def quiet_noisy_loggers() -> None:
    """faiss' loader logs its failed optional-library probes at INFO; only its warnings are worth reading."""
    logging.getLogger("faiss.loader").setLevel(logging.WARNING)
    logging.getLogger("faiss").setLevel(logging.WARNING)


quiet_noisy_loggers()


class JsonFormatter(logging.Formatter):
    """Format a record as one JSON object per line."""

    def format(self, record: logging.LogRecord) -> str:
        doc: dict[str, Any] = {
            "ts": _dt.datetime.fromtimestamp(record.created, _dt.UTC).isoformat(timespec="milliseconds")
            .replace("+00:00", "Z"),
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
        }
        if record.name == "uvicorn.access" and isinstance(record.args, tuple) and len(record.args) == 5:
            client, method, path, _http, status = record.args
            doc.update(client=client, method=method, path=path, status=status)
        for key, value in vars(record).items():
            if key not in _STANDARD_ATTRS and key not in doc:
                doc[key] = value
        if record.exc_info:
            doc["exc"] = self.formatException(record.exc_info)
        return json.dumps(doc, default=str)


class _OurHandler(logging.StreamHandler):  # type: ignore[type-arg]
    """Marks the handler installed here so a second ``configure_logging`` replaces it."""


def configure_logging(level: str = "INFO", fmt: Literal["json", "text"] = "json") -> None:
    """Route every log record (ours, uvicorn's, arq's) to one stderr handler in one format.

    Replaces plain stream handlers on the root logger (``logging.basicConfig``'s) and the handlers uvicorn
    and arq install on their own loggers; leaves other handlers (e.g. pytest's capture) alone.
    """
    root = logging.getLogger()
    for h in list(root.handlers):
        if type(h) is logging.StreamHandler or isinstance(h, _OurHandler):
            root.removeHandler(h)
    handler = _OurHandler(sys.stderr)
    handler.setFormatter(JsonFormatter() if fmt == "json" else
                         logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root.addHandler(handler)
    root.setLevel(level.upper())
    for name in _FOREIGN_LOGGERS:
        lg = logging.getLogger(name)
        lg.handlers.clear()
        lg.propagate = True
    quiet_noisy_loggers()
