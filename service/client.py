"""A small synchronous client for the ReRadar service (httpx), for vehicles and scripts.

    with ReRadarClient("http://127.0.0.1:8080") as client:
        result = client.localize("demo", scan_path="scan.png")
        if result.status == "localized":
            print(result.pose.x_m, result.pose.y_m, result.pose.yaw_deg)
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import httpx

from service.api.schemas import LocalizeResponse, MapInfo, MapList, ReadyResponse, RetrieveResponse, ScanInfo

__all__ = ["ReRadarClient", "ReRadarAPIError"]


class ReRadarAPIError(Exception):
    """The service answered with an error status.

    Attributes:
        status_code: HTTP status; detail: the service's message; error: its error code.
    """

    def __init__(self, status_code: int, detail: str, error: str | None) -> None:
        super().__init__(f"HTTP {status_code} ({error}): {detail}")
        self.status_code = status_code
        self.detail = detail
        self.error = error


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
    """

    def __init__(self, base_url: str, api_key: str | None = None, timeout: float = 60.0,
                 transport: httpx.BaseTransport | None = None) -> None:
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
        if resp.status_code >= 400:
            try:
                body = resp.json()
                detail = body.get("detail") if isinstance(body, dict) else body
                error = body.get("error") if isinstance(body, dict) else None
            except ValueError:
                detail, error = resp.text, None
            raise ReRadarAPIError(resp.status_code, str(detail), error)
        return resp

    # ---- health ------------------------------------------------------------------------------------------
    def healthz(self) -> bool:
        return self._http.get("/healthz").status_code == 200

    def ready(self) -> ReadyResponse:
        resp = self._http.get("/readyz")
        if resp.status_code not in (200, 503):
            self._check(resp)
        return ReadyResponse.model_validate(resp.json())

    def wait_ready(self, timeout_s: float = 120.0, poll_s: float = 0.2) -> ReadyResponse:
        """Poll ``/readyz`` until the service is ready (raises TimeoutError)."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                r = self.ready()
                if r.status == "ready":
                    return r
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise TimeoutError(f"service not ready after {timeout_s:.0f} s")
            time.sleep(poll_s)

    def metrics(self) -> str:
        return self._check(self._http.get("/metrics")).text

    # ---- maps --------------------------------------------------------------------------------------------
    def list_maps(self) -> MapList:
        return MapList.model_validate(self._check(self._http.get("/maps")).json())

    def get_map(self, map_id: str) -> MapInfo:
        return MapInfo.model_validate(self._check(self._http.get(f"/maps/{map_id}")).json())

    def register_map(self, map_id: str, map_path: str | Path) -> MapInfo:
        """Upload a prebuilt HDF5 map."""
        p = Path(map_path)
        with p.open("rb") as fh:
            resp = self._http.post("/maps", data={"map_id": map_id},
                                   files={"map_file": (p.name, fh, "application/x-hdf5")})
        return MapInfo.model_validate(self._check(resp).json())

    def register_map_from_scans(self, map_id: str, archive_path: str | Path, poses_path: str | Path,
                                preset: str | None = None) -> MapInfo:
        """Upload a scan archive + poses; the server builds the map in the background (poll ``wait_for_map``)."""
        a, p = Path(archive_path), Path(poses_path)
        data = {"map_id": map_id, **({"preset": preset} if preset else {})}
        with a.open("rb") as fa, p.open("rb") as fp:
            resp = self._http.post("/maps", data=data, files={"archive": (a.name, fa, "application/octet-stream"),
                                                               "poses": (p.name, fp, "text/csv")})
        return MapInfo.model_validate(self._check(resp).json())

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
        return MapInfo.model_validate(self._check(self._http.delete(f"/maps/{map_id}")).json())

    # ---- scans, retrieval, localization ------------------------------------------------------------------
    def upload_scan(self, scan_path: str | Path | None = None, scan_bytes: bytes | None = None,
                    filename: str = "scan.png", preset: str | None = None,
                    scan_layout: str | None = None, map_id: str | None = None) -> ScanInfo:
        """``POST /scans``; ``map_id``: the map the scan is for (its preset is used when ``preset`` is None)."""
        files = {"scan": _scan_file(scan_path, scan_bytes, filename)}
        data = {k: v for k, v in (("preset", preset), ("scan_layout", scan_layout), ("map_id", map_id)) if v}
        return ScanInfo.model_validate(self._check(self._http.post("/scans", files=files, data=data)).json())

    def _scan_request(self, path: str, fields: dict[str, Any], scan_id: str | None,
                      scan_path: str | Path | None, scan_bytes: bytes | None, filename: str) -> httpx.Response:
        fields = {k: v for k, v in fields.items() if v is not None}
        if scan_id is not None:
            return self._check(self._http.post(path, json={"scan_id": scan_id, **fields}))
        files = {"scan": _scan_file(scan_path, scan_bytes, filename)}
        return self._check(self._http.post(path, data={k: str(v) for k, v in fields.items()}, files=files))

    def retrieve(self, map_id: str, scan_id: str | None = None, scan_path: str | Path | None = None,
                 scan_bytes: bytes | None = None, top_k: int | None = None,
                 filename: str = "scan.png", scan_layout: str | None = None) -> RetrieveResponse:
        fields = {"top_k": top_k, "scan_layout": scan_layout if scan_id is None else None}
        resp = self._scan_request(f"/maps/{map_id}/retrieve", fields, scan_id, scan_path, scan_bytes, filename)
        return RetrieveResponse.model_validate(resp.json())

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
        return LocalizeResponse.model_validate(resp.json())
