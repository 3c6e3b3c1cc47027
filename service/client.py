"""A small synchronous client for the ReRadar service (httpx), for vehicles and scripts.

    with ReRadarClient("http://127.0.0.1:8080") as client:
        result = client.localize("demo", scan_path="scan.png")
        if result.status == "localized":
            print(result.pose.x_m, result.pose.y_m, result.pose.yaw_deg)

Every answer is checked before it is returned: an error status raises ``ReRadarAPIError``, a body that is not the
expected ReRadar JSON (another service, a proxy's HTML page) ``ReRadarResponseError``; a map id that is not a
valid id (``MAP_ID_PATTERN``) is refused with ``ValueError`` before anything is sent.
"""

from __future__ import annotations

import re
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any, TypeVar

import httpx
from pydantic import BaseModel, ValidationError

from service.api.schemas import LocalizeResponse, MapInfo, MapList, ReadyResponse, RetrieveResponse, ScanInfo

# service.core.ids loads nothing else (service.core.config would pull the server's settings and pipeline)
from service.core.ids import MAP_ID_PATTERN

__all__ = ["ReRadarClient", "ReRadarAPIError", "ReRadarResponseError", "MAP_ID_PATTERN", "check_map_id"]

_Model = TypeVar("_Model", bound=BaseModel)

#: statuses ``wait_ready`` waits out: the service starting (503), or a proxy in front of it that cannot reach it
#: yet (502, 504), whatever their body
_NOT_YET = (502, 503, 504)


class ReRadarAPIError(Exception):
    """The service answered with an error status.

    Attributes:
        status_code: HTTP status; detail: the service's message (or the start of a body that is no problem
        answer); error: its error code (None when the body has none).
    """

    def __init__(self, status_code: int, detail: str, error: str | None) -> None:
        super().__init__(f"HTTP {status_code}" + (f" ({error})" if error else "") + f": {detail}")
        self.status_code = status_code
        self.detail = detail
        self.error = error


class ReRadarResponseError(ReRadarAPIError):
    """The server answered with a body that is not the ReRadar response expected: not JSON, or JSON of another
    shape. Usually the base URL names another service (or a proxy's page), or the server is another version.

    ``status_code`` is the answer's status, ``error`` is ``"invalid_response"``, ``detail`` (and ``str()``) a
    message saying what came back and where.
    """

    def __init__(self, status_code: int, detail: str) -> None:
        super().__init__(status_code, detail, "invalid_response")
        self.args = (detail,)  # the message says what came back: no "HTTP 200 (invalid_response)" before it


def check_map_id(map_id: str) -> str:
    """``map_id`` when it is a valid map id (``MAP_ID_PATTERN``, the server's rule), else ValueError.

    Checked before a map id becomes part of a URL path: ``..``, ``/``, ``?`` or ``#`` in it would otherwise
    make the request name another resource (``delete_map("x/../demo")`` deleting ``demo``)."""
    if not isinstance(map_id, str) or re.fullmatch(MAP_ID_PATTERN, map_id) is None:
        raise ValueError(f"invalid map id {map_id!r}: a map id is 1-64 lower-case letters, digits, '_' and '-', "
                         f"starting with a letter or digit ({MAP_ID_PATTERN})")
    return map_id


def _drop_unknown_fields(body: Any, exc: ValidationError) -> bool:
    """Remove from ``body`` (in place) the fields that ``exc`` reports as unknown (``extra_forbidden``); whether
    there were any. A server newer than this client may add response fields, which an older vehicle-side
    client must read past rather than refuse the whole answer."""
    errors = [e for e in exc.errors(include_url=False, include_input=False, include_context=False)
              if e["type"] == "extra_forbidden"]
    for e in errors:
        *parents, name = e["loc"]
        node = body
        for part in parents:
            node = node[part]
        node.pop(name, None)
    return bool(errors)


def _read_model(body: Any, model: type[_Model]) -> _Model:
    """``body`` (parsed JSON) as ``model``, reading past the fields ``model`` does not know (``body`` loses them:
    ``_drop_unknown_fields``). Raises ValidationError for anything else, a known field's error included."""
    try:
        return model.model_validate(body)
    except ValidationError as exc:
        if not _drop_unknown_fields(body, exc):
            raise
    return model.model_validate(body)


def _ready_line(status_code: int, answer: ReadyResponse) -> str:
    """A ``/readyz`` answer in a line: ``HTTP 503 not_ready (no map can be served: ...)``."""
    return f"HTTP {status_code} {answer.status}" + (f" ({answer.reason})" if answer.reason else "")


def _content_type(resp: httpx.Response) -> str:
    return resp.headers.get("content-type", "").split(";")[0].strip() or "no content type"


def _snippet(text: str, limit: int = 200) -> str:
    """``text`` on one line, cut at ``limit`` characters: enough to recognise a proxy's page in an error line."""
    flat = " ".join(text.split())
    return flat if len(flat) <= limit else flat[:limit] + "..."


def _scan_file(scan_path: str | Path | None, scan_bytes: bytes | None, filename: str) -> tuple[str, bytes, str]:
    if (scan_path is None) == (scan_bytes is None):
        raise ValueError("give exactly one of scan_path or scan_bytes")
    if scan_path is not None:
        p = Path(scan_path)
        return p.name, p.read_bytes(), "image/png" if p.suffix.lower() == ".png" else "application/octet-stream"
    return filename, scan_bytes or b"", "image/png" if filename.lower().endswith(".png") else "application/octet-stream"


class ReRadarClient:
    """Client for one ReRadar server.

    Args:
        base_url: e.g. ``http://127.0.0.1:8080``.
        api_key: sent as ``X-API-Key`` (needed for registering and deleting maps).
        timeout: seconds per request.
        transport: optional httpx transport (tests).

    Raises:
        ValueError: ``base_url`` is not an ``http://`` or ``https://`` URL with a host.
    """

    def __init__(self, base_url: str, api_key: str | None = None, timeout: float = 60.0,
                 transport: httpx.BaseTransport | None = None) -> None:
        # refused here, in one line, rather than as httpx's InvalidURL / UnsupportedProtocol at the first request
        try:
            url = httpx.URL(base_url)
        except (httpx.InvalidURL, TypeError) as exc:
            raise ValueError(f"invalid server URL {base_url!r} ({exc}); give e.g. http://127.0.0.1:8080") from None
        if url.scheme not in ("http", "https") or not url.host:
            raise ValueError(f"invalid server URL {base_url!r}: it needs http:// or https:// and a host, "
                             "e.g. http://127.0.0.1:8080")
        # what httpx accepts but no server can be: a port beyond 65535 (reported as "cannot reach" before), a
        # host with a space, a query (every request would go to the base path's own query)
        problem = ("a port from 1 to 65535" if url.port is not None and not 1 <= url.port <= 65535 else
                   "a host without spaces" if "%20" in url.host or " " in url.host else
                   "no query string" if url.query else None)
        if problem is not None:
            raise ValueError(f"invalid server URL {base_url!r}: it needs {problem}, e.g. http://127.0.0.1:8080")
        if api_key and not (api_key.isascii() and api_key.isprintable() and api_key.strip() == api_key
                            and " " not in api_key):
            # httpx refuses such a header value only when sending, which read as "cannot reach" the server
            raise ValueError("invalid API key (--api-key / RERADAR_CLIENT_API_KEY): it holds whitespace, a line "
                             "break or non-ASCII characters; give the key exactly as issued")
        headers = {"X-API-Key": api_key} if api_key else {}
        # plain-HTTP servers need no TLS context, and loading the CA bundle costs ~0.2 s of a vehicle-side
        # call's start-up; redirects are not followed, so requests never leave this http:// base URL
        tls = not base_url.lower().startswith("http://")
        self._http = httpx.Client(base_url=base_url.rstrip("/"), headers=headers, timeout=timeout,
                                  transport=transport, verify=tls)

    def __enter__(self) -> ReRadarClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _check(self, resp: httpx.Response) -> httpx.Response:
        """``resp`` when its status is below 400, else ReRadarAPIError with the problem body's ``detail`` and
        ``error`` (or, for a body that is no problem answer, its start on one line)."""
        if resp.status_code >= 400:
            try:
                body = resp.json()
            except ValueError:  # a proxy's HTML page, plain text, or nothing
                body = None
            if isinstance(body, dict) and "detail" in body:
                detail, error = body["detail"], body.get("error")
            else:
                # e.g. a proxy's "502 Bad Gateway" page: its reason, type and start say where it came from
                text = _snippet(resp.text)
                detail = f"{resp.reason_phrase or 'error'} ({_content_type(resp)})" + (f": {text}" if text else "")
                error = None
            raise ReRadarAPIError(resp.status_code, str(detail), str(error) if error is not None else None)
        return resp

    def _parse(self, resp: httpx.Response, model: type[_Model]) -> _Model:
        """``resp``'s body as ``model`` after ``_check``; ReRadarResponseError when the body is not JSON or not
        that model: every answer the client returns is read here."""
        self._check(resp)
        try:
            body = resp.json()
        except ValueError:  # JSONDecodeError, or bytes that are not UTF-8
            raise self._unexpected(resp, f"something that is not a ReRadar response ({_content_type(resp)}, "
                                         "not JSON)") from None
        try:
            return _read_model(body, model)
        except ValidationError as exc:
            # the first problem only, without the input (it may be a whole page of JSON)
            errs = exc.errors(include_url=False, include_input=False, include_context=False)
            what = f"{'.'.join(str(part) for part in errs[0]['loc']) or 'body'}: {errs[0]['msg']}"
            more = f" and {len(errs) - 1} more" if len(errs) > 1 else ""
            raise self._unexpected(resp, f"JSON that is not a ReRadar {model.__name__} ({what}{more})",
                                   ", of this client's version") from None

    def _unexpected(self, resp: httpx.Response, what: str, also: str = "") -> ReRadarResponseError:
        base = self._http.base_url
        return ReRadarResponseError(resp.status_code, f"the server at {base} answered {resp.status_code} to "
                                                      f"{resp.request.method} {resp.request.url.path} with {what}: "
                                                      f"is {base} the ReRadar API{also}?")

    # ---- health ------------------------------------------------------------------------------------------
    def healthz(self) -> bool:
        return self._http.get("/healthz").status_code == 200

    def ready(self) -> ReadyResponse:
        """``GET /readyz``: the service's answer, ready or not (its 503 carries a ``not_ready`` body). Any other
        error status, and a 503 without that body (a proxy's page), raise ReRadarAPIError."""
        resp = self._http.get("/readyz")
        return self._ready_answer(resp)

    def _ready_answer(self, resp: httpx.Response) -> ReadyResponse:
        if resp.status_code == 503:
            try:
                return _read_model(resp.json(), ReadyResponse)
            except ValueError:  # not the service's own not-ready answer (a proxy's page): the 503 is the error
                pass
        return self._parse(resp, ReadyResponse)  # ReRadarAPIError for any error status

    def wait_ready(self, timeout_s: float = 120.0, poll_s: float = 0.2) -> ReadyResponse:
        """Poll ``/readyz`` until the service is ready.

        Waited out until ``timeout_s``: a connection error, a 502 / 503 / 504 (whatever its body: the service
        starting, or a proxy in front of it that cannot reach it yet) and a ``not_ready`` answer; then
        TimeoutError naming the last answer. Another error status (401, 404) raises ReRadarAPIError, and a 200
        that is no ReRadar answer ReRadarResponseError, at once: waiting fixes neither a wrong URL nor a wrong key.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                resp = self._http.get("/readyz")
            except httpx.TransportError as exc:
                last = f"cannot connect: {exc}"
            else:
                if resp.status_code in _NOT_YET:
                    try:
                        last = _ready_line(resp.status_code, self._ready_answer(resp))
                    except ReRadarAPIError as exc:
                        last = str(exc)
                else:
                    r = self._ready_answer(resp)
                    if r.status == "ready":
                        return r
                    last = _ready_line(resp.status_code, r)
            if time.monotonic() > deadline:
                raise TimeoutError(f"service not ready after {timeout_s:g} s (last answer: {last})")
            time.sleep(poll_s)

    def metrics(self) -> str:
        return self._check(self._http.get("/metrics")).text

    # ---- maps --------------------------------------------------------------------------------------------
    def list_maps(self) -> MapList:
        return self._parse(self._http.get("/maps"), MapList)

    def get_map(self, map_id: str) -> MapInfo:
        """``GET /maps/{map_id}`` (ValueError for an invalid map id, ``check_map_id``)."""
        return self._parse(self._http.get(f"/maps/{check_map_id(map_id)}"), MapInfo)

    def register_map(self, map_id: str, map_path: str | Path, far_map_path: str | Path | None = None) -> MapInfo:
        """Upload a prebuilt HDF5 map; ``far_map_path``: with its far-view companion (the ``<map>.far.h5`` that
        ``reradar build-map --far-view`` wrote with it), served with the map (``MapInfo.far_view``); a companion
        that does not hold the map's keyframes is refused (422) and nothing is registered."""
        p = Path(map_path)
        with ExitStack() as stack:
            files = {"map_file": (p.name, stack.enter_context(p.open("rb")), "application/x-hdf5")}
            if far_map_path is not None:
                f = Path(far_map_path)
                files["far_map_file"] = (f.name, stack.enter_context(f.open("rb")), "application/x-hdf5")
            resp = self._http.post("/maps", data={"map_id": map_id}, files=files)
        return self._parse(resp, MapInfo)

    def register_map_from_scans(self, map_id: str, archive_path: str | Path, poses_path: str | Path,
                                preset: str | None = None, far_view: bool = False) -> MapInfo:
        """Upload a scan archive + poses; the server builds the map in the background (poll ``wait_for_map``).
        ``far_view``: also build its far-view companion (about as long again as the map's own build: 1.8x for 120 scans; docs/SERVICE.md,
        "The far view"); a service that serves no far view refuses it (400)."""
        a, p = Path(archive_path), Path(poses_path)
        data = {"map_id": map_id, **({"preset": preset} if preset else {}), **({"far_view": "true"} if far_view else {})}
        with a.open("rb") as fa, p.open("rb") as fp:
            resp = self._http.post("/maps", data=data, files={"archive": (a.name, fa, "application/octet-stream"),
                                                               "poses": (p.name, fp, "text/csv")})
        return self._parse(resp, MapInfo)

    def wait_for_map(self, map_id: str, timeout_s: float = 600.0, poll_s: float = 0.5) -> MapInfo:
        """Poll ``GET /maps/{id}`` until the map is ready (raises ReRadarAPIError-like RuntimeError on failure)."""
        deadline = time.monotonic() + timeout_s
        while True:
            info = self.get_map(map_id)
            if info.state == "ready":
                return info
            if info.state == "failed":
                raise RuntimeError(f"building map {map_id!r} failed: {info.error}")
            if time.monotonic() > deadline:
                raise TimeoutError(f"map {map_id!r} not ready after {timeout_s:.0f} s ({info.progress:.0%})")
            time.sleep(poll_s)

    def delete_map(self, map_id: str) -> MapInfo:
        """``DELETE /maps/{map_id}`` (ValueError for an invalid map id, ``check_map_id``)."""
        return self._parse(self._http.delete(f"/maps/{check_map_id(map_id)}"), MapInfo)

    # ---- scans, retrieval, localization ------------------------------------------------------------------
    def upload_scan(self, scan_path: str | Path | None = None, scan_bytes: bytes | None = None,
                    filename: str = "scan.png", preset: str | None = None,
                    scan_layout: str | None = None, map_id: str | None = None) -> ScanInfo:
        """``POST /scans``; ``map_id``: the map the scan is for (its preset is used when ``preset`` is None)."""
        files = {"scan": _scan_file(scan_path, scan_bytes, filename)}
        data = {k: v for k, v in (("preset", preset), ("scan_layout", scan_layout), ("map_id", map_id)) if v}
        return self._parse(self._http.post("/scans", files=files, data=data), ScanInfo)

    def _scan_request(self, path: str, fields: dict[str, Any], scan_id: str | None,
                      scan_path: str | Path | None, scan_bytes: bytes | None, filename: str) -> httpx.Response:
        fields = {k: v for k, v in fields.items() if v is not None}
        if scan_id is not None:
            return self._http.post(path, json={"scan_id": scan_id, **fields})
        files = {"scan": _scan_file(scan_path, scan_bytes, filename)}
        return self._http.post(path, data={k: str(v) for k, v in fields.items()}, files=files)

    def retrieve(self, map_id: str, scan_id: str | None = None, scan_path: str | Path | None = None,
                 scan_bytes: bytes | None = None, top_k: int | None = None,
                 filename: str = "scan.png", scan_layout: str | None = None) -> RetrieveResponse:
        """``POST /maps/{map_id}/retrieve`` (ValueError for an invalid map id, ``check_map_id``)."""
        fields = {"top_k": top_k, "scan_layout": scan_layout if scan_id is None else None}
        resp = self._scan_request(f"/maps/{check_map_id(map_id)}/retrieve", fields, scan_id, scan_path, scan_bytes,
                                  filename)
        return self._parse(resp, RetrieveResponse)

    def localize(self, map_id: str, scan_path: str | Path | None = None, scan_id: str | None = None,
                 scan_bytes: bytes | None = None, top_k: int | None = None,
                 filename: str = "scan.png", session_id: str | None = None,
                 odometry: tuple[float, float, float] | None = None,
                 prior: tuple[float, float, float] | None = None,
                 prior_sigma: tuple[float, float] | None = None,
                 scan_layout: str | None = None, preset: str | None = None) -> LocalizeResponse:
        """Localize an inline scan (``scan_path``/``scan_bytes``, multipart) or a cached ``scan_id`` (JSON).

        ``scan_layout="navtech"`` with ``filename="scan.npy"``: ``scan_bytes`` is ``np.save`` of the Navtech image
        itself (uint8, 11 metadata columns + range bins, as the PNG's pixels): the same answer as the PNG, without
        the server's PNG decompression (docs/SERVICE.md). ``preset``: the inline scan's radar preset (range
        geometry; default: inferred by the server).

        Tracking mode: ``session_id`` (the server keeps the session's last pose) with ``odometry`` = motion
        since the session's previous scan (dx m forward, dy m left, dyaw deg, in that scan's frame); or an
        explicit ``prior`` = (x m, y m, yaw deg) in the map frame with ``prior_sigma`` = (m, deg).
        """
        fields: dict[str, Any] = {"map_id": map_id, "top_k": top_k, "session_id": session_id,
                                  "scan_layout": scan_layout if scan_id is None else None,
                                  "preset": preset if scan_id is None else None}
        if odometry is not None:
            fields.update(zip(("odom_dx_m", "odom_dy_m", "odom_dyaw_deg"), map(float, odometry), strict=True))
        if prior is not None:
            fields.update(zip(("prior_x_m", "prior_y_m", "prior_yaw_deg"), map(float, prior), strict=True))
        if prior_sigma is not None:
            fields.update(zip(("prior_sigma_m", "prior_sigma_yaw_deg"), map(float, prior_sigma), strict=True))
        resp = self._scan_request("/localize", fields, scan_id, scan_path, scan_bytes, filename)
        return self._parse(resp, LocalizeResponse)
