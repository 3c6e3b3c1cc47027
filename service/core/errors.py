"""The service's one error model (RFC 9457 problem details) and its service-level errors.

Every error response, whatever raised it (a route, request validation, the router's 404/405, the ASGI guard
that refuses a request before its body is read), is ``application/problem+json``::

    {"type": "urn:reradar:error:scan_format", "title": "Unprocessable Content", "status": 422,
     "detail": "what is wrong and what to do", "error": "scan_format", "instance": "/localize",
     "errors": [{"loc": ["body", "top_k"], "msg": "Input should be a valid integer", "type": "int_type"}]}

``error`` repeats the last part of ``type`` as a short machine-readable code; ``errors`` is present on
request validation errors only. Messages never carry server paths (``scrub_paths``).
"""

from __future__ import annotations

import json
import re
import sys
import tempfile
from collections.abc import Iterable, Sequence
from http import HTTPStatus
from pathlib import Path
from typing import Any

from reradar_core.errors import MAX_ECHOED_CHARS, shorten_echo

__all__ = ["ServiceError", "NotFoundError", "ConflictError", "PayloadTooLargeError", "BadRequestError",
           "ServiceUnavailableError", "UnauthorizedError", "UnsupportedMediaError", "RequestTimeoutError",
           "OverloadedError", "PROBLEM_MEDIA_TYPE", "problem_body", "problem_type", "scrub_paths",
           "validation_detail", "shorten_echo", "MAX_ECHOED_CHARS"]

PROBLEM_MEDIA_TYPE = "application/problem+json"
_TYPE_PREFIX = "urn:reradar:error:"


class ServiceError(Exception):
    """Base class; ``status_code`` and ``code`` go into the problem body, ``headers`` into the response."""

    status_code = 400
    code = "bad_request"

    def __init__(self, message: str, headers: dict[str, str] | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.headers = headers or {}


class BadRequestError(ServiceError):
    status_code = 400
    code = "bad_request"


class UnauthorizedError(ServiceError):
    status_code = 401
    code = "unauthorized"

    def __init__(self, message: str) -> None:
        super().__init__(message, {"WWW-Authenticate": 'ApiKey header="X-API-Key"'})


class NotFoundError(ServiceError):
    status_code = 404
    code = "not_found"


class RequestTimeoutError(ServiceError):
    status_code = 408
    code = "request_timeout"


class ConflictError(ServiceError):
    status_code = 409
    code = "conflict"


class PayloadTooLargeError(ServiceError):
    status_code = 413
    code = "payload_too_large"


class UnsupportedMediaError(ServiceError):
    status_code = 415
    code = "unsupported_media_type"


class TooManyRequestsError(ServiceError):
    """The caller (its API key) already has as many requests in progress as one key may (429 + Retry-After)."""

    status_code = 429
    code = "too_many_requests"

    def __init__(self, message: str, retry_after_s: int = 1) -> None:
        super().__init__(message, {"Retry-After": str(retry_after_s)})


class ServiceUnavailableError(ServiceError):
    status_code = 503
    code = "not_ready"

    def __init__(self, message: str, retry_after_s: int = 5) -> None:
        super().__init__(message, {"Retry-After": str(retry_after_s)})


class OverloadedError(ServiceUnavailableError):
    code = "overloaded"


def problem_type(code: str) -> str:
    """The problem ``type`` URI of an error code."""
    return _TYPE_PREFIX + code


def _default_roots() -> list[str]:
    roots = {tempfile.gettempdir(), str(Path.cwd()), sys.prefix, str(Path(__file__).resolve().parents[2]),
             str(Path.home())}
    return sorted((r for r in roots if len(r) > 1), key=len, reverse=True)


def scrub_paths(message: str, roots: Iterable[str | Path] = ()) -> str:
    """``message`` with every absolute path under one of ``roots`` (plus the temp folder, the working folder,
    the install prefix and the home folder) replaced by its last component, so that no error shows where the
    server keeps its files."""
    all_roots = sorted({str(r) for r in roots if len(str(r)) > 1} | set(_default_roots()), key=len, reverse=True)
    for root in all_roots:
        pattern = re.escape(root.rstrip("/")) + r"(?![^/\s'\":,;()])(?:/[^\s'\":,;()]*)?"
        message = re.sub(pattern, lambda m: Path(m.group(0)).name or "(server folder)", message)
    return message


#: Validation errors returned as ``errors`` items (the ``detail`` counts them all): an answer stays small
#: whatever the request.
MAX_REPORTED_ERRORS = 20


def validation_detail(errors: Sequence[dict[str, Any]]) -> tuple[str, list[dict[str, Any]]]:
    """A one-line ``detail`` and JSON-safe ``errors`` items (``loc``, ``msg``, ``type``; the first
    ``MAX_REPORTED_ERRORS``) from pydantic / FastAPI validation errors. The offending ``input`` and ``ctx`` are dropped: they may be bytes that are
    not UTF-8 or floats that JSON cannot hold (NaN, inf), and echoing them back helps nobody."""
    items = []
    for e in errors[:MAX_REPORTED_ERRORS]:
        # a field name is the client's text: echoed in full, a 7 MB key made a 14 MB answer
        loc = [x if isinstance(x, int) else shorten_echo(str(x)) for x in e.get("loc", ())]
        items.append({"loc": loc, "msg": shorten_echo(str(e.get("msg", "invalid value")), 300),
                      "type": str(e.get("type", "value_error"))})
    parts = [f"{'.'.join(str(x) for x in i['loc'][1:] or i['loc']) or 'body'}: {i['msg']}" for i in items[:5]]
    more = f" (+{len(errors) - 5} more)" if len(errors) > 5 else ""
    return "invalid request: " + "; ".join(parts) + more, items


def problem_body(status: int, code: str, detail: str, instance: str | None = None,
                 errors: list[dict[str, Any]] | None = None) -> bytes:
    """The serialized problem document (always valid JSON: non-finite floats cannot reach it)."""
    try:
        title = HTTPStatus(status).phrase
    except ValueError:
        title = "Error"
    body: dict[str, Any] = {"type": problem_type(code), "title": title, "status": status, "detail": detail,
                            "error": code}
    if instance is not None:  # the request's path, the client's text: cut as names are
        body["instance"] = shorten_echo(instance, 256)
    if errors is not None:
        body["errors"] = errors
    return json.dumps(body, ensure_ascii=False, allow_nan=False).encode("utf-8", "replace")
