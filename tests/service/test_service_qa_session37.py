"""Session 37: the offline API docs' vendored assets come without source-map comments (the package ships no .map
files, so browsers' developer tools asked for one and logged a 404); what a deleted map left behind (QA)."""

from __future__ import annotations

import shutil
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import httpx
import pytest

from maps.database import MapDatabase
from reradar_core.io.scan import encode_navtech_png_bytes
from service.api.routes.ui import _SOURCE_MAP_LINE

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import API_KEY, keyframe_time, make_scan, started_app, upload_map_file  # noqa: E402


@pytest.fixture
def client(server: tuple[str, Path]) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server[0], timeout=30) as c:
        yield c


@pytest.mark.parametrize("asset, media", [("swagger-ui.css", "text/css"), ("redoc.standalone.js", "javascript"),
                                          ("swagger-ui-bundle.js", "javascript")])
def test_vendored_docs_assets_name_no_missing_source_map(client: httpx.Client, asset: str, media: str) -> None:
    r = client.get(f"/ui/vendor/{asset}")
    assert r.status_code == 200 and media in r.headers["content-type"]
    assert b"sourceMappingURL=" not in r.content.split(b"\n")[-1]
    assert not _SOURCE_MAP_LINE.search(r.content)
    assert int(r.headers["content-length"]) == len(r.content) > 10_000  # the asset itself, only the comment gone
    assert r.headers.get("etag")
    again = client.get(f"/ui/vendor/{asset}", headers={"If-None-Match": r.headers["etag"]})
    assert again.status_code == 304  # browsers' caching still works
    assert client.get(f"/ui/vendor/{asset}.map").status_code == 404


def test_source_map_comment_lines_only_are_removed() -> None:
    css = b"a{b:c}\n/*# sourceMappingURL=swagger-ui.css.map*/"
    js = b"var s = 'x //# sourceMappingURL=inside.a.string';\n//# sourceMappingURL=redoc.standalone.js.map\n"
    assert _SOURCE_MAP_LINE.sub(b"", css) == b"a{b:c}\n"
    assert _SOURCE_MAP_LINE.sub(b"", js) == b"var s = 'x //# sourceMappingURL=inside.a.string';\n"


# ---- QA session 37: what a deleted map leaves behind ---------------------------------------------------------------
AUTH = {"X-API-Key": API_KEY}


def _other_version(fake_map: Path, out: Path) -> Path:
    """The same keyframes as ``fake_map`` with another creation time: another map version."""
    shutil.copy(fake_map, out)
    with h5py.File(out, "r+") as f:
        f.attrs["created_utc"] = "2030-01-01T00:00:00Z"
    return out


def test_an_answer_finishing_after_its_map_was_deleted_is_not_shown_on_the_new_map(
        fake_map: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """QA: a localization in flight while its map was deleted and another registered under the id was recorded
    under the id, so the operator page showed the new map vehicles at the old map's positions."""
    in_flight, replaced = threading.Event(), threading.Event()
    localize = MapDatabase.localize

    def paused_localize(self: MapDatabase, *args: Any, **kwargs: Any) -> Any:
        if not in_flight.is_set():
            in_flight.set()
            assert replaced.wait(30)
        return localize(self, *args, **kwargs)

    monkeypatch.setattr(MapDatabase, "localize", paused_localize)
    png = encode_navtech_png_bytes(make_scan(3, keyframe_time(3)))
    answers: list[Any] = []
    with started_app(tmp_path / "maps") as client:
        assert upload_map_file(client, fake_map, "x").status_code == 201
        request = threading.Thread(target=lambda: answers.append(client.post(
            "/localize", data={"map_id": "x"}, files={"scan": ("s.png", png)}, headers=AUTH)))
        request.start()
        try:
            assert in_flight.wait(30)
            assert client.delete("/maps/x", headers=AUTH).status_code == 200
            r = upload_map_file(client, _other_version(fake_map, tmp_path / "other.h5"), "x")
            assert r.status_code == 201, r.text
        finally:
            replaced.set()
            request.join(60)
        assert answers and answers[0].status_code == 200 and answers[0].json()["status"] == "localized"
        shown = client.get("/ui/api/maps/x/localizations", headers=AUTH).json()
        assert shown["count"] == 0 and shown["data"] == []  # the old map's answer is not the new map's
        r = client.post("/localize", data={"map_id": "x"}, files={"scan": ("s.png", png)}, headers=AUTH)
        assert r.status_code == 200
        shown = client.get("/ui/api/maps/x/localizations", headers=AUTH).json()
        assert shown["count"] == 1 and shown["data"][0]["keyframe_id"] == r.json()["keyframe"]["keyframe_id"]
        assert "map_version" not in shown["data"][0]  # bookkeeping, not part of the record shown


def test_a_deleted_maps_arrays_file_is_removed_at_once_unless_another_map_uses_it(
        fake_map: Path, tmp_path: Path) -> None:
    """QA: DELETE left the map's shared arrays file (~100 MB for a 2,000-keyframe map) until a restart at least 10
    minutes later; a quick register/delete cycle grew the folder by a file each time."""
    maps_dir = tmp_path / "maps"
    with started_app(maps_dir) as client:
        arrays = maps_dir / ".arrays"
        assert upload_map_file(client, fake_map, "a").status_code == 201
        assert upload_map_file(client, fake_map, "b").status_code == 201  # the same keyframes: the same file
        other = _other_version(fake_map, tmp_path / "other.h5")
        assert upload_map_file(client, other, "c").status_code == 201
        files = sorted(p.name for p in arrays.glob("*.rrarr"))
        assert len(files) >= 1
        assert client.delete("/maps/a", headers=AUTH).status_code == 200
        assert sorted(p.name for p in arrays.glob("*.rrarr")) == files  # "b" still maps it
        assert client.delete("/maps/b", headers=AUTH).status_code == 200
        assert client.delete("/maps/c", headers=AUTH).status_code == 200
        assert list(arrays.glob("*.rrarr")) == []


# ---- QA session 37: one key cannot take every request slot -------------------------------------------------------
def _held_app():  # type: ignore[no-untyped-def]
    """An app whose scan requests wait until ``release`` is set; ``entered`` counts those waiting."""
    import asyncio

    state = {"entered": 0, "release": asyncio.Event()}

    async def app(scope, receive, send):  # type: ignore[no-untyped-def]
        while (await receive()).get("more_body"):
            pass
        if scope["path"] == "/localize":
            state["entered"] += 1
            await state["release"].wait()
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ok"})

    return app, state


@pytest.mark.parametrize("keyless", [False, True])
def test_one_key_holds_at_most_its_share_of_the_request_slots(keyless: bool) -> None:
    """QA: four slow uploads with one vehicle key held all four request slots, so every other vehicle got 503 for
    as long as they kept it up. One key now holds at most ``max_concurrent_per_key`` (429 beyond, with
    Retry-After); other keys still get in; keyless loopback clients (a local setup) are not limited per key."""
    import asyncio

    from service.api.middleware import RequestGuardMiddleware
    from service.api.security import AccessPolicy, Guard, RequestLimits
    from service.core.errors import PROBLEM_MEDIA_TYPE

    ka, kb, kc = "vehicle-key-A-0123456789", "vehicle-key-B-0123456789", "vehicle-key-C-0123456789"
    limits = RequestLimits(1000, 1000, 5.0, 5.0, 5.0, max_concurrent=3, retry_after_s=2, max_concurrent_per_key=2)
    # keyless loopback clients are served only where no vehicle keys are configured; the operator key then fills up
    guard = Guard(AccessPolicy("o" * 20, () if keyless else (ka, kb, kc)), limits)
    if keyless:
        kc = "o" * 20
    app, state = _held_app()
    guarded = RequestGuardMiddleware(app, get_guard=lambda: guard, default_limits=lambda: limits)

    async def run() -> dict[str, httpx.Response | list[httpx.Response]]:
        transport = httpx.ASGITransport(app=guarded)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            def post(key: str | None) -> Any:
                return asyncio.create_task(c.post("/localize", content=b"x",
                                                  headers={"X-API-Key": key} if key else {}))

            async def entered(n: int) -> None:
                for _ in range(500):
                    if state["entered"] >= n:
                        return
                    await asyncio.sleep(0.01)
                raise AssertionError(f"{state['entered']} requests reached the app, expected {n}: "
                                     f"{[t.result().status_code for t in held if t.done()]}")

            held = [post(None if keyless else ka), post(None if keyless else ka)]
            await entered(2)
            third = await asyncio.wait_for(post(ka), 5) if not keyless else None
            # keyless: not limited per key, a third keyless request takes the last slot; else another vehicle gets in
            held.append(post(None if keyless else kb))
            await entered(3)
            full = await c.post("/localize", content=b"x", headers={"X-API-Key": kc})
            state["release"].set()
            done = [await t for t in held]
            after = await c.post("/localize", content=b"x", headers={"X-API-Key": kc})  # slots given back
            return {"third": third, "full": full, "done": done, "after": after}

    out = asyncio.run(run())
    assert [r.status_code for r in out["done"]] == [200, 200, 200]  # type: ignore[union-attr]
    if not keyless:
        third = out["third"]
        assert third.status_code == 429 and third.headers["content-type"] == PROBLEM_MEDIA_TYPE  # type: ignore[union-attr]
        assert third.headers["retry-after"] == "2" and third.json()["error"] == "too_many_requests"  # type: ignore[union-attr]
        assert "already has 2 scan / map requests in progress" in third.json()["detail"]  # type: ignore[union-attr]
    full = out["full"]
    assert full.status_code == 503 and full.json()["error"] == "overloaded"  # type: ignore[union-attr]
    assert out["after"].status_code == 200  # type: ignore[union-attr]
    assert guarded.in_flight == 0 and guarded.in_flight_by_caller == {}


def test_an_unknown_scan_layout_is_not_echoed_at_length(client: httpx.Client) -> None:
    """QA: a 100,000-character `scan_layout` came back whole in the 400 of /localize and /retrieve."""
    from service.api.scan_input import parse_scan_layout
    from service.core.errors import BadRequestError

    with pytest.raises(BadRequestError) as err:
        parse_scan_layout("x" * 100_000)
    assert len(err.value.message) < 400 and "100,000 characters" in err.value.message
    r = client.post("/scans", data={"scan_layout": "x" * 100_000}, files={"scan": ("s.npy", b"\x93NUMPY")})
    assert 400 <= r.status_code < 500 and len(r.content) < 4000, (r.status_code, len(r.content))


def test_a_scan_id_is_its_uploaders(tmp_path: Path, fake_map: Path) -> None:
    """QA: a scan uploaded with key A could be used by key B and the operator key (tracking sessions were already
    each caller's own). Now another caller's scan_id is unknown to it (404, as an expired one)."""
    from service_test_fakes import FakeExtractor, register_map_file

    from service.core.config import Settings
    from service.demo import serve_in_thread

    key_a, key_b = "vehicle-key-A-0123456789", "vehicle-key-B-0123456789"
    settings = Settings(maps_dir=tmp_path / "maps", load_demo_map=False, api_key=API_KEY,
                        vehicle_keys=f"{key_a},{key_b}")
    png = encode_navtech_png_bytes(make_scan(2, keyframe_time(2)))
    with serve_in_thread(settings, FakeExtractor()) as url, httpx.Client(base_url=url, timeout=60) as c:
        register_map_file(c, fake_map, "m")
        up = c.post("/scans", files={"scan": ("s.png", png)}, headers={"X-API-Key": key_a})
        assert up.status_code == 201, up.text
        scan_id = up.json()["scan_id"]
        for key, status in ((key_b, 404), (API_KEY, 404), (key_a, 200)):
            r = c.post("/localize", json={"map_id": "m", "scan_id": scan_id}, headers={"X-API-Key": key})
            assert r.status_code == status, (key[:8], r.text)
        r = c.post("/maps/m/retrieve", json={"scan_id": scan_id}, headers={"X-API-Key": key_b})
        assert r.status_code == 404 and "unknown or expired scan_id" in r.json()["detail"]


def test_public_map_source_shows_no_build_path() -> None:
    """QA session 38: the public GET /maps showed the build machine's absolute path in ``source``."""
    from service.api.routes.maps import public_source

    assert public_source("boreas:/home/ops/runs/2021-09-02") == "boreas:2021-09-02"
    assert public_source("mulran:C:\\data\\DCC01") == "mulran:DCC01"
    assert public_source("upload:archive.zip") == "upload:archive.zip"
    assert public_source(None) is None
