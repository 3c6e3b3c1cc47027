"""QA (client robustness): the vehicle client and `reradar localize` against ids, URLs and answers they did not
expect. Map ids are checked before they become part of a URL path (`delete_map("nosuch/../demo2")` deleted map
`demo2`); an answer that is not the ReRadar API's (a proxy's HTML page, another service's JSON) is one
`ReRadarResponseError` and one `error:` line with exit 2, not a traceback with exit 1 (which means "not
localized"); `wait_ready` waits out a proxy's 502 / 503 / 504; `--follow --out` is checked before the replay.

Fake answers come from ``httpx.MockTransport`` (no network), and once from a tiny HTTP server on an ephemeral
loopback port (the real transport)."""

from __future__ import annotations

import http.server
import json
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx
import pytest
import typer
from typer.testing import CliRunner

from reradar_core.io.datasets import write_sequence_poses, write_sequence_scan
from reradar_core.io.poses import PoseSequence
from reradar_core.io.scan import encode_navtech_png_bytes
from service import client as client_module
from service.cli import register
from service.client import MAP_ID_PATTERN, ReRadarAPIError, ReRadarClient, ReRadarResponseError, check_map_id
from service.follow import trajectory_path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import keyframe_poses, keyframe_time, make_scan  # noqa: E402

Handler = Callable[[httpx.Request], httpx.Response]

HTML = "<html>\r\n<head><title>502 Bad Gateway</title></head>\r\n<body><center>nginx</center></body>\r\n</html>"
READY = {"status": "ready", "model_id": "m", "weights_sha256": None, "maps_ready": 1, "maps_total": 1}
NOT_READY = {**READY, "status": "not_ready"}
MAP = {"id": "demo", "state": "ready", "progress": 1.0, "registered_utc": "2024-01-01T00:00:00Z"}
NOT_LOCALIZED = {"status": "not_localized", "reason": "no_candidate", "map_id": "m", "scan_id": None,
                 "timings_ms": {"total_ms": 1.0}}

#: ids that would name another resource (or none) once in a path, and ids the server refuses anyway
BAD_IDS = ["nosuch/../demo2", "demo?x=1", "../healthz", "../maps/demo", "demo#x", "..", "demo/", "Demo", "",
           "-demo", "_demo", "a" * 65, "demo\n", "dé", "demo%2f..", " demo"]


def _client(handler: Handler, seen: list[httpx.Request] | None = None) -> ReRadarClient:
    def record(request: httpx.Request) -> httpx.Response:
        if seen is not None:
            seen.append(request)
        return handler(request)

    return ReRadarClient("http://x", transport=httpx.MockTransport(record))


def _answer(status: int, body: object = None, content: bytes | None = None,
            content_type: str = "application/json") -> Handler:
    raw = content if content is not None else json.dumps(body).encode()
    return lambda request: httpx.Response(status, content=raw, headers={"content-type": content_type})


def _fake_cli_server(monkeypatch: pytest.MonkeyPatch, handler: Handler) -> list[httpx.Request]:
    """Every request the CLI's client sends, recorded and answered by ``handler`` (no network)."""
    seen: list[httpx.Request] = []

    def record(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return handler(request)

    init = client_module.ReRadarClient.__init__
    monkeypatch.setattr(client_module.ReRadarClient, "__init__",
                        lambda self, base_url, **kw: init(self, base_url, transport=httpx.MockTransport(record)))
    return seen


def _app() -> typer.Typer:
    app = typer.Typer()
    register(app)
    return app


def _one_error_line(output: str) -> str:
    lines = [ln for ln in output.splitlines() if ln.strip()]
    assert "Traceback" not in output and len([ln for ln in lines if ln.startswith("error: ")]) == 1, output
    return next(ln for ln in lines if ln.startswith("error: "))


# ---- map ids ---------------------------------------------------------------------------------------------


def test_client_map_id_rule_is_the_servers() -> None:
    from service.api.schemas import MapInfo  # noqa: F401 - the schemas' rule is the same object
    from service.core import config, ids

    assert MAP_ID_PATTERN == config.MAP_ID_PATTERN == ids.MAP_ID_PATTERN
    assert check_map_id("demo") == "demo" and check_map_id("a_b-1") == "a_b-1" and check_map_id("0" * 64)


@pytest.mark.parametrize("map_id", BAD_IDS)
def test_client_refuses_map_ids_before_they_reach_a_path(map_id: str) -> None:
    seen: list[httpx.Request] = []
    with _client(_answer(200, MAP), seen) as rc:
        calls = [lambda: rc.get_map(map_id), lambda: rc.delete_map(map_id),
                 lambda: rc.wait_for_map(map_id, timeout_s=0.1),
                 lambda: rc.retrieve(map_id, scan_id="s1"), lambda: rc.retrieve(map_id, scan_bytes=b"png")]
        for call in calls:
            with pytest.raises(ValueError, match="invalid map id") as exc:
                call()
            assert MAP_ID_PATTERN in str(exc.value) and "lower-case letters, digits" in str(exc.value)
    assert seen == []  # refused before anything is sent


def test_client_sends_a_valid_map_id_as_the_path_segment() -> None:
    seen: list[httpx.Request] = []
    with _client(_answer(200, MAP), seen) as rc:
        assert rc.get_map("demo").id == "demo"
        assert rc.delete_map("demo-2_b").id == "demo"
    assert [(r.method, r.url.path, r.url.query) for r in seen] == [("GET", "/maps/demo", b""),
                                                                  ("DELETE", "/maps/demo-2_b", b"")]


# ---- base URL --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("url", ["http://[::1", "ftp://x", "127.0.0.1:8080", "localhost:8080", "http://", "", "x",
                                 "http://127.0.0.1:70000", "http://a b", "http://127.0.0.1:8774/?x=1"])
def test_client_refuses_a_base_url_that_is_not_http(url: str) -> None:
    with pytest.raises(ValueError, match="invalid server URL"):
        ReRadarClient(url)


@pytest.mark.parametrize("url", ["http://[::1", "ftp://x", "127.0.0.1:8080"])
def test_localize_command_refuses_a_bad_server_url_with_exit_2(url: str, tmp_path: Path) -> None:
    scan = tmp_path / "q.png"
    scan.write_bytes(b"png")
    res = CliRunner().invoke(_app(), ["localize", str(scan), "--server", url])
    assert res.exit_code == 2, res.output
    line = _one_error_line(res.output)
    assert line.startswith("error: --server: invalid server URL") and "http://127.0.0.1:8080" in line


# ---- answers that are not the ReRadar API's ---------------------------------------------------------------


CALLS: dict[str, Callable[[ReRadarClient], object]] = {
    "list_maps": lambda rc: rc.list_maps(),
    "get_map": lambda rc: rc.get_map("demo"),
    "delete_map": lambda rc: rc.delete_map("demo"),
    "upload_scan": lambda rc: rc.upload_scan(scan_bytes=b"png"),
    "retrieve": lambda rc: rc.retrieve("demo", scan_id="s1"),
    "localize": lambda rc: rc.localize("demo", scan_bytes=b"png"),
    "localize_scan_id": lambda rc: rc.localize("demo", scan_id="s1"),
    "ready": lambda rc: rc.ready(),
    "wait_ready": lambda rc: rc.wait_ready(timeout_s=0.1, poll_s=0.01),
}


@pytest.mark.parametrize("call", sorted(CALLS))
def test_client_raises_a_response_error_on_an_html_answer(call: str) -> None:
    with _client(_answer(200, content=b"<html><body>hello</body></html>", content_type="text/html")) as rc:
        with pytest.raises(ReRadarResponseError) as exc:
            CALLS[call](rc)
    err = exc.value
    assert isinstance(err, ReRadarAPIError) and err.status_code == 200 and err.error == "invalid_response"
    assert err.detail == str(err) == err.args[0] and str(err).startswith("the server at http://x answered 200 to ")
    assert "not a ReRadar response (text/html, not JSON): is http://x the ReRadar API?" in str(err)


@pytest.mark.parametrize("call", sorted(CALLS))
@pytest.mark.parametrize("body", [{"foo": 1}, [1, 2], "ok", None])
def test_client_raises_a_response_error_on_json_of_another_shape(call: str, body: object) -> None:
    with _client(_answer(200, body)) as rc:
        with pytest.raises(ReRadarResponseError) as exc:
            CALLS[call](rc)
    assert "with JSON that is not a ReRadar " in str(exc.value) and "is http://x the ReRadar API" in str(exc.value)
    assert exc.value.status_code == 200


def test_client_response_error_on_bytes_that_are_not_utf8() -> None:
    with _client(_answer(200, content=b"\xff\xfe\x00garbage", content_type="application/octet-stream")) as rc:
        with pytest.raises(ReRadarResponseError, match=r"\(application/octet-stream, not JSON\)"):
            rc.list_maps()


def test_client_names_the_first_schema_problem() -> None:
    with _client(_answer(200, {"foo": 1})) as rc:
        with pytest.raises(ReRadarResponseError) as exc:
            rc.localize("demo", scan_bytes=b"png")
    assert ("answered 200 to POST /localize with JSON that is not a ReRadar LocalizeResponse (status: Field "
            "required and 3 more)") in str(exc.value)


def test_client_reports_an_error_page_by_status_reason_and_start() -> None:
    with _client(_answer(502, content=HTML.encode(), content_type="text/html")) as rc:
        with pytest.raises(ReRadarAPIError) as exc:
            rc.list_maps()
    err = exc.value
    assert type(err) is ReRadarAPIError and err.status_code == 502 and err.error is None
    assert str(err).startswith("HTTP 502: Bad Gateway (text/html): <html> <head><title>502 Bad Gateway")
    assert "\n" not in str(err) and "(None)" not in str(err)
    with _client(_answer(404, {"detail": "unknown map 'x'", "error": "unknown_map"})) as rc:
        with pytest.raises(ReRadarAPIError, match=r"^HTTP 404 \(unknown_map\): unknown map 'x'$"):
            rc.get_map("x")


# ---- readiness -------------------------------------------------------------------------------------------


def test_ready_reports_a_proxys_503_as_an_error_and_the_services_as_not_ready() -> None:
    with _client(_answer(503, content=b"<html>Service Unavailable</html>", content_type="text/html")) as rc:
        with pytest.raises(ReRadarAPIError) as exc:
            rc.ready()
    assert exc.value.status_code == 503 and not isinstance(exc.value, ReRadarResponseError)
    with _client(_answer(503, NOT_READY)) as rc:
        assert rc.ready().status == "not_ready"


def test_wait_ready_polls_through_gateway_errors_and_connection_errors() -> None:
    answers: list[Callable[[httpx.Request], httpx.Response]] = [
        lambda r: (_ for _ in ()).throw(httpx.ConnectError("refused", request=r)),
        _answer(502, content=HTML.encode(), content_type="text/html"),
        _answer(503, content=b"<html>Service Unavailable</html>", content_type="text/html"),
        _answer(504, content=b""),
        _answer(503, NOT_READY),
        _answer(200, NOT_READY),
        _answer(200, READY),
    ]
    seen: list[httpx.Request] = []
    with _client(lambda r: answers[len(seen) - 1](r), seen) as rc:
        assert rc.wait_ready(timeout_s=10, poll_s=0.001).status == "ready"
    assert len(seen) == len(answers)


def test_wait_ready_times_out_naming_the_last_answer() -> None:
    seen: list[httpx.Request] = []
    with _client(_answer(502, content=HTML.encode(), content_type="text/html"), seen) as rc:
        with pytest.raises(TimeoutError) as exc:
            rc.wait_ready(timeout_s=0.2, poll_s=0.02)
    assert len(seen) > 2  # it kept polling
    assert str(exc.value).startswith("service not ready after 0.2 s (last answer: HTTP 502: Bad Gateway (text/html)")
    with _client(_answer(503, NOT_READY)) as rc:
        with pytest.raises(TimeoutError, match=r"last answer: HTTP 503 not_ready\)"):
            rc.wait_ready(timeout_s=0.05, poll_s=0.01)


def test_wait_ready_fails_at_once_on_a_wrong_key_or_url() -> None:
    for handler, error in [(_answer(401, {"detail": "missing API key", "error": "unauthorized"}), ReRadarAPIError),
                           (_answer(404, content=b"Not Found", content_type="text/plain"), ReRadarAPIError),
                           (_answer(200, content=b"<html/>", content_type="text/html"), ReRadarResponseError)]:
        seen: list[httpx.Request] = []
        with _client(handler, seen) as rc:
            with pytest.raises(error):
                rc.wait_ready(timeout_s=5, poll_s=0.01)
        assert len(seen) == 1


# ---- `reradar localize` ------------------------------------------------------------------------------------


@pytest.mark.parametrize(("status", "content", "content_type", "expect"), [
    (200, b"<html><body>hello</body></html>", "text/html",
     "answered 200 to POST /localize with something that is not a ReRadar response (text/html, not JSON): is "
     "http://x the ReRadar API?"),
    (200, b'{"foo": 1}', "application/json", "with JSON that is not a ReRadar LocalizeResponse (status: Field"),
    (502, HTML.encode(), "text/html", "HTTP 502: Bad Gateway (text/html): <html>"),
])
def test_localize_command_reports_an_unexpected_answer_in_one_line(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path, status: int, content: bytes, content_type: str,
        expect: str) -> None:
    _fake_cli_server(monkeypatch, _answer(status, content=content, content_type=content_type))
    scan = tmp_path / "q.png"
    scan.write_bytes(b"png")
    res = CliRunner().invoke(_app(), ["localize", str(scan), "--server", "http://x"])
    assert res.exit_code == 2 and isinstance(res.exception, SystemExit), res.output  # 1 means "not localized"
    assert expect in _one_error_line(res.output)


def test_localize_command_reports_an_undecodable_body_in_one_line(monkeypatch: pytest.MonkeyPatch,
                                                                  tmp_path: Path) -> None:
    _fake_cli_server(monkeypatch, lambda r: httpx.Response(200, content=b"not gzip", headers={
        "content-encoding": "gzip", "content-type": "application/json"}))
    scan = tmp_path / "q.png"
    scan.write_bytes(b"png")
    res = CliRunner().invoke(_app(), ["localize", str(scan), "--server", "http://x"])
    assert res.exit_code == 2, res.output
    assert "answered with a body that cannot be decoded" in _one_error_line(res.output)


@pytest.fixture
def html_server() -> Iterator[str]:
    """A real HTTP server on an ephemeral loopback port answering every request 200 with an HTML page."""

    class Page(http.server.BaseHTTPRequestHandler):
        def _page(self) -> None:
            self.rfile.read(int(self.headers.get("content-length") or 0))
            body = b"<!doctype html><html><body>Welcome to nginx!</body></html>"
            self.send_response(200)
            self.send_header("content-type", "text/html; charset=utf-8")
            self.send_header("content-length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        do_GET = do_POST = _page

        def log_message(self, *args: object) -> None:
            pass

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Page)
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{srv.server_address[1]}"
    finally:
        srv.shutdown()
        srv.server_close()
        thread.join(5)


def test_localize_command_against_a_web_server_that_is_not_reradar(html_server: str, tmp_path: Path) -> None:
    scan = tmp_path / "q.png"
    scan.write_bytes(encode_navtech_png_bytes(make_scan(2, 0)))
    res = CliRunner().invoke(_app(), ["localize", str(scan), "--server", html_server])
    assert res.exit_code == 2, res.output
    assert _one_error_line(res.output) == (
        f"error: the server at {html_server} answered 200 to POST /localize with something that is not a ReRadar "
        f"response (text/html, not JSON): is {html_server} the ReRadar API?")


# ---- `reradar localize --follow --out` ---------------------------------------------------------------------


def _drive(root: Path, n: int = 3, t0_us: int = keyframe_time(0) + 10_000_000) -> Path:
    """A Boreas-layout folder of ``n`` scans 0.25 s apart from ``t0_us`` (absolute UTC by default; a small
    ``t0_us`` makes the pose file's times relative), with poses at their mid-sweep times. It does not name its
    radar (no simulator record): a replay passes ``--preset boreas``."""
    seq = root / "drive"
    times = [t0_us + i * 250_000 for i in range(n)]
    for i, t in enumerate(times):
        write_sequence_scan(seq, "boreas", make_scan(i, t))
    poses = keyframe_poses()[:n]
    write_sequence_poses(seq, "boreas", PoseSequence([t + 124_688 for t in times], poses[:, :2], poses[:, 2]))
    return seq


def test_trajectory_path_rules(tmp_path: Path) -> None:
    seq = tmp_path / "drive"
    seq.mkdir()
    out_dir = tmp_path / "plots"
    out_dir.mkdir()
    assert trajectory_path(None, seq) == tmp_path / "drive-follow.png"
    assert trajectory_path(out_dir, seq) == out_dir / "drive-follow.png"  # an existing folder: inside it
    assert trajectory_path(tmp_path / "t.PNG", seq) == tmp_path / "t.PNG"
    for bad, why in [(tmp_path / "t.txt", "ending in .png"), (tmp_path / "plot", "ending in .png"),
                     (tmp_path / "t.png.svg", "ending in .png"),
                     (tmp_path / "missing" / "deeper" / "t.png", f"folder {tmp_path / 'missing' / 'deeper'} does "
                                                                 "not exist")]:
        with pytest.raises(ValueError) as exc:
            trajectory_path(bad, seq)
        assert why in str(exc.value)
    assert not (tmp_path / "missing").exists()
    (tmp_path / "afile").write_text("x")
    with pytest.raises(ValueError, match="afile is a file, not a folder"):
        trajectory_path(tmp_path / "afile" / "x.png", seq)


@pytest.mark.parametrize(("out", "expect"), [
    ("x.txt", "the trajectory is written as a PNG; give a file name ending in .png"),
    ("noext", "the trajectory is written as a PNG"),
    ("missing/dir/x.png", "does not exist (it is not created"),
])
def test_follow_checks_out_before_the_replay(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, out: str,
                                             expect: str) -> None:
    seen = _fake_cli_server(monkeypatch, _answer(200, NOT_LOCALIZED))
    seq = _drive(tmp_path)
    res = CliRunner().invoke(_app(), ["localize", "--follow", str(seq), "--server", "http://x", "--map", "m",
                                      "--preset", "boreas", "--out", str(tmp_path / out)])
    assert res.exit_code == 2, res.output
    assert expect in _one_error_line(res.output)
    assert seen == []  # nothing was replayed
    assert not (tmp_path / "missing").exists() and not list(tmp_path.glob("*.png"))


def test_follow_out_existing_folder_writes_inside_and_prints_the_path(monkeypatch: pytest.MonkeyPatch,
                                                                      tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    seen = _fake_cli_server(monkeypatch, _answer(200, NOT_LOCALIZED))
    seq = _drive(tmp_path)
    plots = tmp_path / "plots"
    plots.mkdir()
    res = CliRunner().invoke(_app(), ["localize", "--follow", str(seq), "--server", "http://x", "--map", "m",
                                      "--preset", "boreas", "--out", str(plots)])
    # not localized is no error answer of the replay, but a replay that localized nothing exits 1 (QA session 38)
    assert res.exit_code == 1, res.output
    assert len(seen) == 3
    png = plots / "drive-follow.png"
    assert f"trajectory: {png}\n" in res.output
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and not (tmp_path / "plots.png").exists()


def test_follow_reports_an_unexpected_answer_in_one_line(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    _fake_cli_server(monkeypatch, _answer(200, content=b"<html/>", content_type="text/html"))
    seq = _drive(tmp_path)
    res = CliRunner().invoke(_app(), ["localize", "--follow", str(seq), "--server", "http://x", "--map", "m",
                                      "--preset", "boreas", "--out", str(tmp_path / "t.png")])
    assert res.exit_code == 2, res.output
    assert "not a ReRadar response (text/html, not JSON)" in _one_error_line(res.output)
    assert not (tmp_path / "t.png").exists()


def test_follow_reads_relative_pose_times_in_the_given_time_unit(monkeypatch: pytest.MonkeyPatch,
                                                                 tmp_path: Path) -> None:
    """QA (session 24, finding 2): a folder whose pose times are relative could not be replayed; the error said to
    pass --time-unit, which `localize` did not have. Now it does, as `build-map --time-unit`: the folder is read
    with it (the ground truth printed is the poses'), and a wrong unit is refused before any scan is sent."""
    pytest.importorskip("matplotlib")
    seen = _fake_cli_server(monkeypatch, _answer(200, NOT_LOCALIZED))
    seq = _drive(tmp_path, t0_us=1_000_000)  # pose times 1.12 .. 1.62 s: no absolute UTC time, unit unknown
    args = ["localize", "--follow", str(seq), "--server", "http://x", "--map", "m", "--preset", "boreas",
            "--out", str(tmp_path / "t.png")]
    res = CliRunner().invoke(_app(), args)
    assert res.exit_code == 2, res.output
    assert "--time-unit s|ms|us|ns" in _one_error_line(res.output) and seen == []
    res = CliRunner().invoke(_app(), [*args, "--time-unit", "ms"])  # 1000x off: refused, naming the likely unit
    assert res.exit_code == 2 and "pass --time-unit us" in _one_error_line(res.output) and seen == []
    res = CliRunner().invoke(_app(), [*args, "--time-unit", "us"])
    assert res.exit_code == 1, res.output  # read and replayed; nothing localized (the fake answers so): exit 1
    assert len(seen) == 3 and all(b'name="preset"\r\n\r\nboreas' in r.content for r in seen)
    rows = [ln.split() for ln in res.output.splitlines() if ln[:4].strip().isdigit()]
    gt = keyframe_poses()[:3]
    assert [(float(r[8]), float(r[9])) for r in rows] == [(round(x, 2), round(y, 2)) for x, y in gt[:, :2]]


def test_time_unit_is_refused_without_follow(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    seen = _fake_cli_server(monkeypatch, _answer(200, NOT_LOCALIZED))
    scan = tmp_path / "q.png"
    scan.write_bytes(encode_navtech_png_bytes(make_scan(2, 0)))
    res = CliRunner().invoke(_app(), ["localize", str(scan), "--server", "http://x", "--time-unit", "us"])
    assert res.exit_code == 2 and "--time-unit is the unit of a --follow folder's pose times" in \
        _one_error_line(res.output)
    res = CliRunner().invoke(_app(), ["localize", "--follow", str(tmp_path), "--server", "http://x",
                                      "--time-unit", "hours"])
    assert res.exit_code == 2 and "must be one of s, ms, us, ns" in res.output
    assert seen == []


def test_client_reads_past_fields_a_newer_server_adds() -> None:
    """Response fields this client does not know (a newer server) are ignored, not a ReRadarResponseError; a
    known field of the wrong type still is one."""
    body = {"data": [{**MAP, "added_later": {"x": 1}}], "count": 1, "page": 2}

    def answer(request: httpx.Request) -> httpx.Response:
        return httpx.Response(200, json=body)

    client = ReRadarClient("http://reradar.test", transport=httpx.MockTransport(answer))
    maps = client.list_maps()
    assert maps.count == 1 and maps.data[0].id == "demo" and maps.data[0].state == "ready"
    body["count"] = "many"
    with pytest.raises(ReRadarResponseError, match="count"):
        client.list_maps()


def test_a_newer_servers_not_ready_answer_is_read_as_not_ready() -> None:
    """The service's own 503 ``not_ready`` with a field this client does not know is still ``not_ready`` (read as
    every other answer is), not an error status."""
    with _client(_answer(503, {**NOT_READY, "warming_up": True})) as rc:
        assert rc.ready().status == "not_ready"


# ---- QA session 38: a replay that meets errors, busy servers and a lost server ----------------------------


def _sequenced(*handlers: Handler) -> Handler:
    """Answer the n-th request with ``handlers[n]`` (the last one from then on)."""
    calls = [0]

    def answer(request: httpx.Request) -> httpx.Response:
        h = handlers[min(calls[0], len(handlers) - 1)]
        calls[0] += 1
        return h(request)
    return answer


def test_follow_goes_on_past_a_refused_scan_and_retries_a_busy_server(monkeypatch: pytest.MonkeyPatch,
                                                                      tmp_path: Path) -> None:
    """A corrupt scan (422) ended the whole replay without a summary; a 503 ``overloaded`` ended it at once."""
    import service.follow as follow

    monkeypatch.setattr(follow, "BUSY_WAIT_S", 0.0)
    bad = _answer(422, {"error": "scan_format", "detail": "upload is not a readable PNG image"},
                  content_type="application/problem+json")
    busy = _answer(503, {"error": "overloaded", "detail": "retry in 1 s"}, content_type="application/problem+json")
    seen = _fake_cli_server(monkeypatch, _sequenced(bad, busy, busy, _answer(200, NOT_LOCALIZED)))
    seq = _drive(tmp_path)
    res = CliRunner().invoke(_app(), ["localize", "--follow", str(seq), "--server", "http://x", "--map", "m",
                                      "--preset", "boreas", "--out", str(tmp_path / "t.png")])
    assert res.exit_code == 1, res.output  # a failed scan, nothing localized
    assert "error: scan 1600000010000000.png: HTTP 422 (scan_format)" in res.output
    assert "failed (an error answer, on stderr): 1/3" in res.output and "not localized: 2/3" in res.output
    assert len(seen) == 5 and (tmp_path / "t.png").exists()  # scan 1 tried three times, scan 2 once


def test_follow_stops_on_an_error_every_scan_would_get_and_on_a_lost_server(monkeypatch: pytest.MonkeyPatch,
                                                                            tmp_path: Path) -> None:
    seq = _drive(tmp_path)
    args = ["localize", "--follow", str(seq), "--server", "http://x", "--map", "m", "--preset", "boreas",
            "--out", str(tmp_path / "t.png")]
    unknown = _answer(404, {"error": "not_found", "detail": "no map 'm'"}, content_type="application/problem+json")
    with pytest.MonkeyPatch.context() as first:  # its own patch: a second one would wrap the first's transport
        seen = _fake_cli_server(first, unknown)
        res = CliRunner().invoke(_app(), args)
    assert res.exit_code == 2 and len(seen) == 1 and "the replay stops here" in _one_error_line(res.output)

    def gone(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("connection refused")

    _fake_cli_server(monkeypatch, _sequenced(_answer(200, NOT_LOCALIZED), gone))
    res = CliRunner().invoke(_app(), args)
    assert res.exit_code == 3 and "the server was lost" in res.output
    assert "not localized: 1/1" in res.output  # the summary of what was replayed


def test_client_refuses_a_key_it_cannot_send_and_localize_says_which_option() -> None:
    for key in ("vehiclekey-0123456789abcdef ", "vehiclekey\n", "véhicule-0123456789abcdef"):
        with pytest.raises(ValueError, match="invalid API key"):
            ReRadarClient("http://127.0.0.1:1", api_key=key)
    res = CliRunner().invoke(_app(), ["localize", "x.png", "--server", "http://127.0.0.1:1", "--api-key", "a b"])
    assert res.exit_code == 2 and "invalid API key (--api-key / RERADAR_CLIENT_API_KEY)" in res.output


def test_single_scan_options_are_refused_with_follow(tmp_path: Path) -> None:
    res = CliRunner().invoke(_app(), ["localize", "--follow", str(tmp_path), "--json"])
    assert res.exit_code == 2 and "--json applies to a single SCAN" in res.output
