"""uvicorn's HTTP/1.1 protocol (h11) with a deadline for each request's head.

uvicorn closes an idle keep-alive connection 5 s after a response, but a connection that never completes a
request line and headers - opened and left silent, or sending a header byte now and then - is never closed:
20,000 of them (no key needed: the request guard sees only complete requests) held +100 MB and every file
descriptor, after which the server accepted no one (QA, session 22). ``HeadTimeoutH11Protocol`` closes a
connection whose next request head is not complete within ``header_timeout_s`` of the connection's start or
of the previous response; the body then runs under the request guard's own timeouts
(``service.api.middleware``). In a fleet nginx buffers requests in front of the replicas as well.
"""

from __future__ import annotations

import asyncio
import os
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

__all__ = ["HeadTimeoutH11Protocol", "HEADER_TIMEOUT_ENV", "DEFAULT_HEADER_TIMEOUT_S"]

#: Environment variable (the ``RERADAR_HEADER_TIMEOUT_S`` setting) read by worker processes that uvicorn spawns
HEADER_TIMEOUT_ENV = "RERADAR_HEADER_TIMEOUT_S"
DEFAULT_HEADER_TIMEOUT_S = 10.0


class HeadTimeoutH11Protocol(H11Protocol):
    """``H11Protocol`` that closes a connection whose request head (request line and headers) is not complete
    within ``header_timeout_s`` seconds of the connection's start or of its previous response. Pass the class
    as uvicorn's ``http``; set ``header_timeout_s`` on the class (one process) or ``HEADER_TIMEOUT_ENV`` (worker
    processes, read at import)."""

    header_timeout_s: float = float(os.environ.get(HEADER_TIMEOUT_ENV) or DEFAULT_HEADER_TIMEOUT_S)

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._head_timer: asyncio.TimerHandle | None = None
        self._arm_head_timer()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._arm_head_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_head_timer()
        super().connection_lost(exc)

    def _waiting_for_head(self, cycle: Any) -> bool:
        # no request on the connection yet, or the last one answered: what arrives now is the next head
        return (self.cycle is cycle and (cycle is None or cycle.response_complete)
                and not self.transport.is_closing())

    def _arm_head_timer(self) -> None:
        self._cancel_head_timer()
        if self._waiting_for_head(self.cycle):  # a pipelined request may already be running
            self._head_timer = self.loop.call_later(self.header_timeout_s, self._head_timed_out, self.cycle)

    def _cancel_head_timer(self) -> None:
        timer = getattr(self, "_head_timer", None)
        if timer is not None:
            timer.cancel()
            self._head_timer = None

    def _head_timed_out(self, cycle: Any) -> None:
        self._head_timer = None
        if not self._waiting_for_head(cycle):  # a request head arrived meanwhile (a new cycle)
            return
        try:
            self.conn.send(h11.ConnectionClosed())
        except h11.LocalProtocolError:  # a partial head makes no difference to our side; close all the same
            pass
        self.transport.close()
