"""A connection that never completes a request head is closed after ``RERADAR_HEADER_TIMEOUT_S`` (QA, session
22: 20,000 silent or half-sent connections were held forever and the server then accepted no one); complete
requests, keep-alive reuse and slow bodies (the request guard's business) are unaffected."""

from __future__ import annotations

import socket
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from service.core.config import Settings
from service.demo import serve_in_thread

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import API_KEY, FakeExtractor  # noqa: E402

TIMEOUT_S = 1.0


@pytest.fixture(scope="module")
def address(tmp_path_factory: pytest.TempPathFactory, fake_extractor: FakeExtractor) -> Iterator[tuple[str, int]]:
    settings = Settings(maps_dir=tmp_path_factory.mktemp("maps"), load_demo_map=False, api_key=API_KEY,
                        torch_threads=1, header_timeout_s=TIMEOUT_S)
    with serve_in_thread(settings, fake_extractor) as url:
        host, port = url.removeprefix("http://").split(":")
        yield host, int(port)


def _closed_after(sock: socket.socket, limit_s: float) -> float | None:
    """Seconds until the server closed ``sock`` (reading whatever it sent), None if still open after ``limit_s``."""
    t0 = time.monotonic()
    sock.settimeout(limit_s)
    try:
        while sock.recv(4096):
            pass
    except TimeoutError:
        return None
    return time.monotonic() - t0


def _get(sock: socket.socket) -> bytes:
    sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: t\r\n\r\n")
    sock.settimeout(5)
    data = b""
    while b"\r\n\r\n" not in data or not data.endswith(b"}"):
        data += sock.recv(4096)
    return data


def test_silent_and_half_sent_connections_are_closed(address: tuple[str, int]) -> None:
    silent = socket.create_connection(address)
    half = socket.create_connection(address)
    half.sendall(b"GET /healthz HTTP/1.1\r\nHost: t\r\nX-A: ")
    for sock in (silent, half):
        took = _closed_after(sock, 4 * TIMEOUT_S)
        assert took is not None and took < 3 * TIMEOUT_S, took
        sock.close()


def test_complete_requests_and_keep_alive_reuse_are_served(address: tuple[str, int]) -> None:
    with socket.create_connection(address) as sock:
        assert _get(sock).startswith(b"HTTP/1.1 200")
        time.sleep(0.6 * TIMEOUT_S)  # within the head timeout of the next request: the connection serves again
        assert _get(sock).startswith(b"HTTP/1.1 200")
        # a head sent slowly but completed in time is answered
        for part in (b"GET /healthz HTTP/1.1\r\n", b"Host: t\r\n", b"\r\n"):
            sock.sendall(part)
            time.sleep(0.25 * TIMEOUT_S)
        sock.settimeout(5)
        assert sock.recv(4096).startswith(b"HTTP/1.1 200")
        # then, silent again: closed (uvicorn's own keep-alive timeout or this one, whichever first)
        assert _closed_after(sock, 8.0) is not None


def test_a_body_slower_than_the_head_timeout_is_not_cut_by_it(address: tuple[str, int]) -> None:
    """After the head, the body runs under the guard's timeouts (1 KiB/s from 5 s, 10 s idle): a 2-byte body sent
    1.5 head-timeouts after its head still gets the application's answer (a 404 for this unknown path)."""
    with socket.create_connection(address) as sock:
        sock.sendall(b"POST /nowhere HTTP/1.1\r\nHost: t\r\nContent-Length: 2\r\nX-API-Key: " + API_KEY.encode()
                     + b"\r\n\r\n")
        time.sleep(1.5 * TIMEOUT_S)
        sock.sendall(b"{}")
        sock.settimeout(5)
        assert sock.recv(4096).split(b"\r\n")[0] == b"HTTP/1.1 404 Not Found"
