"""Service infrastructure: settings validation, scan cache bounds/expiry, metrics text, archive safety."""

from __future__ import annotations

import io
import stat
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from reradar_core.features import ScanFeatures
from service.core.archive import extract_scan_archive
from service.core.config import DEV_API_KEY, OPERATOR_KEY_FILE, Settings, resolve_operator_key
from service.core.errors import BadRequestError, NotFoundError, PayloadTooLargeError
from service.core.metrics import Metrics
from service.core.scan_cache import ScanCache


def test_keys_have_no_usable_default(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    with pytest.raises(ValidationError, match="RERADAR_API_KEY"):
        Settings(environment="production", maps_dir=tmp_path)
    with pytest.raises(ValidationError, match="RERADAR_VEHICLE_KEYS"):
        Settings(environment="production", api_key="x" * 32, maps_dir=tmp_path)
    with pytest.raises(ValidationError, match="published development key"):
        Settings(api_key=DEV_API_KEY, maps_dir=tmp_path)
    with pytest.raises(ValidationError, match="at least 16"):
        Settings(vehicle_keys="v" * 20 + ",short", maps_dir=tmp_path)
    ok = Settings(environment="production", api_key="x" * 32, vehicle_keys=" a" * 10 + ", " + "b" * 16,
                  maps_dir=tmp_path)
    assert ok.api_key is not None and ok.api_key.get_secret_value() == "x" * 32
    assert ok.vehicle_key_list == [("a " * 10).strip(), "b" * 16]
    assert resolve_operator_key(ok) == "x" * 32
    # no key configured: a random one is generated once, stored with mode 0600 and reused after a restart
    dev = Settings(maps_dir=tmp_path / "maps")
    assert dev.api_key is None and dev.vehicle_key_list == []
    key = resolve_operator_key(dev)
    stored = tmp_path / "maps" / OPERATOR_KEY_FILE
    assert len(key) >= 16 and key != DEV_API_KEY and stored.read_text().strip() == key
    assert stat.S_IMODE(stored.stat().st_mode) == 0o600
    assert resolve_operator_key(Settings(maps_dir=tmp_path / "maps")) == key
    assert resolve_operator_key(Settings(maps_dir=tmp_path / "other")) != key
    monkeypatch.setenv("RERADAR_LOCALIZATION__TOP_K", "7")
    monkeypatch.setenv("RERADAR_LOCALIZATION__ALIGNMENT__SCREEN_HYPOTHESES", "700")
    monkeypatch.setenv("RERADAR_MAX_UPLOAD_MB", "1.5")
    s = Settings(maps_dir=tmp_path)
    assert s.localization.top_k == 7 and s.max_upload_bytes == int(1.5 * 2**20)
    assert s.localization.alignment.screen_hypotheses == 700 and s.localization.verify_k == 1
    assert s.localization.prescreen_keep == 5
    monkeypatch.setenv("RERADAR_LOCALIZATION__PRESCREEN_KEEP", "none")  # "none" unsets an optional setting
    monkeypatch.setenv("RERADAR_LOCALIZATION__EXPANSION_BLOCK", "10")
    s = Settings(maps_dir=tmp_path)
    assert s.localization.prescreen_keep is None and s.localization.expansion_block == 10
    monkeypatch.delenv("RERADAR_LOCALIZATION__PRESCREEN_KEEP")
    monkeypatch.delenv("RERADAR_LOCALIZATION__EXPANSION_BLOCK")
    monkeypatch.setenv("RERADAR_LOCALIZATION__TOP_K", "0")
    with pytest.raises(ValidationError):
        Settings(maps_dir=tmp_path)
    monkeypatch.delenv("RERADAR_LOCALIZATION__TOP_K")
    monkeypatch.setenv("RERADAR_TOP_K", "7")  # the old flat name is refused, not silently ignored
    with pytest.raises(ValidationError, match="RERADAR_LOCALIZATION__TOP_K"):
        Settings(maps_dir=tmp_path)
    monkeypatch.delenv("RERADAR_TOP_K")


@pytest.mark.parametrize("text", ["[3, 2, 0.5]", "(3, 2, 0.5)", "3,2,0.5", " 3, 2, 0.5 ", "3 2 0.5", "3,2,0.5,"])
def test_tuple_settings_are_read_from_their_nested_variables(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                                             text: str) -> None:
    """QA (session 30): RERADAR_LOCALIZATION__MOTION__RADII_M was refused as "Input should be a valid tuple" in
    every form (pydantic-settings decodes JSON only for top-level fields); only the whole-JSON form worked."""
    monkeypatch.setenv("RERADAR_LOCALIZATION__MOTION__RADII_M", text)
    monkeypatch.setenv("RERADAR_LOCALIZATION__ALIGNMENT__REFINE_THRESHOLDS_M", text)
    s = Settings(maps_dir=tmp_path)
    assert s.localization.motion.radii_m == (3.0, 2.0, 0.5)
    assert s.localization.alignment.refine_thresholds_m == (3.0, 2.0, 0.5)
    monkeypatch.setenv("RERADAR_LOCALIZATION__MOTION__RADII_M", "3, two")  # still a settings error, not a guess
    with pytest.raises(ValidationError, match="radii_m"):
        Settings(maps_dir=tmp_path)
    monkeypatch.setenv("RERADAR_LOCALIZATION__MOTION__RADII_M", "60, 1")  # and still validated by the config
    with pytest.raises(ValidationError, match="at most 10 m"):
        Settings(maps_dir=tmp_path)


def test_misspelt_settings_are_refused_or_reported(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """QA (session 21): RERADAR_LOCALIZATION__TOPK=3 started a server that used top_k 10, and a typo in
    RERADAR_NETWORK_RUNTIME ended in a traceback (exit 3) instead of the one-line settings error (exit 2)."""
    from service.core.config import unknown_variables

    for name, value, message in (("RERADAR_LOCALIZATION__TOPK", "3", "did you mean RERADAR_LOCALIZATION__TOP_K"),
                                 ("RERADAR_LOCALIZATION__ALIGNMENT__SCREEN_HYPOTHESE", "8", "SCREEN_HYPOTHESES"),
                                 ("RERADAR_NETWORK_RUNTIME", "gpu", "auto, onnx, torch")):
        monkeypatch.setenv(name, value)
        with pytest.raises(ValidationError, match=message):
            Settings(maps_dir=tmp_path)
        monkeypatch.delenv(name)
    # the JSON form of the same settings: a misspelt key is refused too (QA re-test, session 21)
    monkeypatch.setenv("RERADAR_LOCALIZATION", '{"topk": 3}')
    with pytest.raises(ValidationError, match="'topk' is no localization setting .did you mean 'top_k'"):
        Settings(maps_dir=tmp_path)
    monkeypatch.setenv("RERADAR_LOCALIZATION", '{"top_k": 3, "alignment": {"screen_hypothese": 9}}')
    with pytest.raises(ValidationError, match="'alignment.screen_hypothese' .*'alignment.screen_hypotheses'"):
        Settings(maps_dir=tmp_path)
    monkeypatch.setenv("RERADAR_LOCALIZATION", '{"top_k": 3}')
    assert Settings(maps_dir=tmp_path).localization.top_k == 3
    monkeypatch.delenv("RERADAR_LOCALIZATION")
    monkeypatch.setenv("RERADAR_LOCALIZATION__ALIGNMENT__SCREEN_HYPOTHESES", "8")  # nested names are known
    assert Settings(maps_dir=tmp_path).localization.alignment.screen_hypotheses == 8
    env = {"RERADAR_TORCH_THREAD": "2", "RERADAR_CACHE_DIR": "/c", "RERADAR_CLIENT_API_KEY": "k", "RERADAR_FOO": "1",
           "RERADAR_MAPS_DIR": "/m", "OTHER": "1"}
    assert unknown_variables(env) == [("RERADAR_FOO", None), ("RERADAR_TORCH_THREAD", "RERADAR_TORCH_THREADS")]


def _feat(i: int) -> ScanFeatures:
    return ScanFeatures(np.ones(4) / 2, np.zeros((0, 2)), np.zeros((0, 8)), i)


def test_scan_cache_is_bounded_lru_with_expiry() -> None:
    now = [0.0]
    cache = ScanCache(max_entries=2, ttl_s=10.0, clock=lambda: now[0], per_owner=2)
    a, b = cache.put(_feat(1), "boreas"), cache.put(_feat(2), None)
    assert a.scan_id != b.scan_id and len(a.scan_id) == 32
    assert cache.get(a.scan_id) is not None  # a is now most recently used
    c = cache.put(_feat(3), None)  # evicts b (least recently used)
    assert cache.get(b.scan_id) is None and cache.get(c.scan_id) is not None and len(cache) == 2
    now[0] = 10.5
    assert cache.get(a.scan_id) is None and len(cache) == 0
    assert cache.get("nope") is None


def test_scan_cache_keeps_each_callers_scans_to_itself_and_to_its_share() -> None:
    """QA session 37: key B uploading 260 scans in 8 s evicted key A's scan (told `expires_in_s: 600`), and any
    key could use another's scan_id. A caller's scans are its own, and one caller holds at most a quarter of the
    cache: beyond that its own oldest goes."""
    cache = ScanCache(max_entries=8, ttl_s=600.0)
    assert cache.per_owner == 2
    a = cache.put(_feat(0), None, owner="key-a")
    b = [cache.put(_feat(i), None, owner="key-b") for i in range(1, 40)]
    assert cache.get(a.scan_id, "key-a") is a  # untouched by B's uploads
    assert cache.get(a.scan_id, "key-b") is None  # not B's to use
    assert [cache.get(e.scan_id, "key-b") is not None for e in b[-3:]] == [False, True, True]  # B's newest two
    assert len(cache) == 3


def test_metrics_prometheus_text() -> None:
    from prometheus_client.parser import text_string_to_metric_families

    m = Metrics()
    m.inc("reradar_http_requests_total", method="GET", route="/maps", status="200")
    m.inc("reradar_http_requests_total", method="GET", route="/maps", status="200")
    m.observe("reradar_http_request_duration_seconds", 0.004, method="GET", route="/maps")
    m.observe_stages({"extract_ms": 30.0, "total_ms": 50.0})
    m.set_gauge("reradar_maps_loaded", 3)
    m.set_model("fake-model", "ab" * 32, "onnx")
    text = m.render()
    samples = {(s.name, tuple(sorted(s.labels.items()))): s.value
               for fam in text_string_to_metric_families(text) for s in fam.samples}
    route = (("method", "GET"), ("route", "/maps"))
    assert samples[("reradar_http_requests_total", (*route, ("status", "200")))] == 2
    assert samples[("reradar_http_request_duration_seconds_bucket", (("le", "0.005"), *route))] == 1
    assert samples[("reradar_http_request_duration_seconds_bucket", (("le", "0.0025"), *route))] == 0
    assert samples[("reradar_stage_duration_seconds_count", (("stage", "extract"),))] == 1
    assert 'stage="total"' not in text
    assert samples[("reradar_maps_loaded", ())] == 3 and "# TYPE reradar_maps_loaded gauge" in text
    # process, build and model info come from prometheus-client's collectors and our Info metrics
    assert ("process_resident_memory_bytes", ()) in samples
    assert samples[("reradar_model_info", (("model_id", "fake-model"), ("network_runtime", "onnx"),
                                          ("weights_sha256", "ab" * 32)))] == 1
    assert any(name == "reradar_build_info" and dict(labels).get("version") for name, labels in samples)


def test_archive_extraction_is_flat_and_bounded(tmp_path: Path) -> None:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        for name, data in [("a/b/1000.png", b"x" * 10), ("../../2000.npy", b"y" * 10), ("notes.txt", b"z"),
                           ("3000.png.exe", b"w")]:
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    arch = tmp_path / "a.tgz"
    arch.write_bytes(buf.getvalue())
    linked = io.BytesIO()
    with tarfile.open(fileobj=linked, mode="w:gz") as tf:
        link = tarfile.TarInfo("4000.png")
        link.type = tarfile.SYMTYPE
        link.linkname = "/etc/passwd"
        tf.addfile(link)
    (tmp_path / "link.tgz").write_bytes(linked.getvalue())
    with pytest.raises(BadRequestError, match="'4000.png' is a link"):  # never followed; said, not skipped
        extract_scan_archive(tmp_path / "link.tgz", tmp_path / "ol", max_files=10, max_total_bytes=1000)
    assert not any((tmp_path / "ol").iterdir())
    out = extract_scan_archive(arch, tmp_path / "out", max_files=10, max_total_bytes=1000)
    assert [p.name for p in out] == ["1000.png", "2000.npy"]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["1000.png", "2000.npy"]
    assert not (tmp_path.parent / "2000.npy").exists()
    with pytest.raises(PayloadTooLargeError):
        extract_scan_archive(arch, tmp_path / "o2", max_files=1, max_total_bytes=1000)
    with pytest.raises(PayloadTooLargeError):
        extract_scan_archive(arch, tmp_path / "o3", max_files=10, max_total_bytes=15)
    zbuf = io.BytesIO()
    with zipfile.ZipFile(zbuf, "w") as zf:
        zf.writestr("x/5.png", b"1")
        zf.writestr("y/5.png", b"2")
    (tmp_path / "d.zip").write_bytes(zbuf.getvalue())
    with pytest.raises(BadRequestError, match="two files"):
        extract_scan_archive(tmp_path / "d.zip", tmp_path / "o4", 10, 1000)
    (tmp_path / "bad.zip").write_bytes(b"PK\x03\x04 broken")
    with pytest.raises(BadRequestError):
        extract_scan_archive(tmp_path / "bad.zip", tmp_path / "o5", 10, 1000)


def test_demo_map_installed_and_refreshed_after_weight_change(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    import service.core.registry as reg
    from maps.store import MapMetadata, read_metadata, write_map

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from service_test_fakes import FakeExtractor

    ext = FakeExtractor()
    feats = [ScanFeatures(np.ones(32) / np.sqrt(32), np.zeros((3, 2)), np.eye(3, 16), 0)]

    def demo_file(path: Path, sha: str, name: str = "demo") -> Path:
        meta = MapMetadata("fake-extractor", sha, "boreas", 201, 0.64, 32, 16, name=name)
        return write_map(path, meta, feats, np.zeros((1, 3)), overwrite=True)

    shipped = demo_file(tmp_path / "shipped.h5", ext.weights_sha256)
    monkeypatch.setattr(reg, "DEMO_MAP_PATH", shipped)
    maps_dir = tmp_path / "maps"
    registry = reg.MapRegistry(Settings(maps_dir=maps_dir), ext)
    registry.install_demo_map()
    registry.load_all()
    assert registry.get("demo").state == "ready"
    registry.close()
    demo_file(maps_dir / "demo.h5", "0" * 64)  # installed by an older image with other weights
    registry = reg.MapRegistry(Settings(maps_dir=maps_dir), ext)
    registry.install_demo_map()
    assert read_metadata(maps_dir / "demo.h5").weights_sha256 == ext.weights_sha256
    registry.close()
    demo_file(maps_dir / "demo.h5", "0" * 64, name="users-own-map")  # not ours: left alone (and refused)
    registry = reg.MapRegistry(Settings(maps_dir=maps_dir), ext)
    registry.install_demo_map()
    registry.load_all()
    entry = registry.get("demo")
    assert entry.state == "failed" and "rebuild the map" in (entry.error or "")
    # QA (session 21): a demo map the operator deleted came back at every start
    registry.delete("demo")
    registry.close()
    registry = reg.MapRegistry(Settings(maps_dir=maps_dir), ext)
    registry.install_demo_map()
    registry.load_all()
    assert not (maps_dir / "demo.h5").exists() and "demo" not in [e.map_id for e in registry.entries()]
    registry.close()
    (maps_dir / reg.DEMO_DELETED_MARKER).unlink()  # what the docs say to do to get it back
    registry = reg.MapRegistry(Settings(maps_dir=maps_dir), ext)
    registry.install_demo_map()
    assert read_metadata(maps_dir / "demo.h5").weights_sha256 == ext.weights_sha256
    registry.close()


def test_unset_keys_from_compose_and_loopback_binding(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("RERADAR_API_KEY", "")  # compose passes unset variables as empty strings
    monkeypatch.setenv("RERADAR_VEHICLE_KEYS", " ")
    s = Settings(maps_dir=tmp_path)
    assert s.api_key is None and s.vehicle_key_list == []
    compose = (Path(__file__).resolve().parents[2] / "docker" / "compose.yaml").read_text()
    assert "${RERADAR_BIND:-127.0.0.1}:${RERADAR_PORT:-8080}:8080" in compose
    assert DEV_API_KEY not in compose and 'RERADAR_API_KEY: "${RERADAR_API_KEY:-}"' in compose


def test_workers_share_map_arrays_across_a_map_update(tmp_path: Path, fake_map: Path) -> None:
    """Two registries on one maps folder (two worker processes' view): one arrays file for the map, shared;
    when the map is replaced (deleted and registered again with other content) the new version gets its own
    file, the registry still holding the old version keeps answering from its mapping, and the old file goes
    at once."""
    import shutil

    from service_test_fakes import FakeExtractor, make_scan

    import service.core.registry as reg
    from maps.store import open_map, write_map

    ext = FakeExtractor()
    maps_dir = tmp_path / "maps"
    maps_dir.mkdir()
    shutil.copyfile(fake_map, maps_dir / "route.h5")
    a = reg.MapRegistry(Settings(maps_dir=maps_dir, load_demo_map=False), ext)
    b = reg.MapRegistry(Settings(maps_dir=maps_dir, load_demo_map=False), ext)
    a.load_all()
    b.load_all()
    db_a, db_b = a.ready("route"), b.ready("route")
    assert db_a.arrays is not None and db_b.arrays is not None
    assert db_a.arrays.path == db_b.arrays.path and len(list((maps_dir / ".arrays").glob("*.rrarr"))) == 1
    query = ext.describe(make_scan(3, 7))
    before = db_b.localize(query)

    with open_map(fake_map) as m:  # the same map with its keyframe order reversed: other content
        feats = [m.read_keyframe(i) for i in reversed(range(len(m)))]
        meta, poses = m.metadata, m.poses[::-1].copy()
    a.delete("route")
    staged = a.staging_dir() / "new.h5"
    write_map(staged, meta, feats, poses)
    a.register_file("route", staged)
    new_path = a.ready("route").arrays.path  # type: ignore[union-attr]
    assert new_path != db_b.arrays.path and new_path.is_file()
    again = db_b.localize(query)  # b has not reloaded yet: the old version, from its own mapping
    assert (again.status, again.best.keyframe_id if again.best else None) == \
           (before.status, before.best.keyframe_id if before.best else None)
    # the deleting registry removed the old version's file at once (QA session 37: it stayed until a restart);
    # b answered above from its own mapping of it, whose pages stay valid
    assert not db_b.arrays.path.exists()
    b.forget("route")
    b.prune_map_arrays()
    assert list((maps_dir / ".arrays").glob("*.rrarr")) == [new_path]
    a.close()
    b.close()


def test_close_closes_every_map_and_delete_lets_requests_in_flight_finish(tmp_path, fake_map):
    """Code audit (session 20): ``MapRegistry.close`` had lost its body (the maps stayed open at shutdown: files,
    memory maps, caches), and ``delete`` closed a map that requests taken before it may still be localizing on
    (they met "map is closed", naming the file). Then the map closed 30 s after the delete, used or not (QA: two
    file descriptors and the deleted file's space held per upload-and-delete cycle); now it closes when the last
    request using it (``MapRegistry.using``) is done, at once when none is."""
    import shutil

    from service_test_fakes import FakeExtractor, make_scan

    import service.core.registry as reg

    ext = FakeExtractor()
    maps_dir = tmp_path / "maps"
    maps_dir.mkdir()
    for name in ("kept", "doomed", "idle"):
        shutil.copyfile(fake_map, maps_dir / f"{name}.h5")
    registry = reg.MapRegistry(Settings(maps_dir=maps_dir, load_demo_map=False, share_map_arrays=False,
                                        preload_keyframes=False, keyframe_cache_size=1), ext)
    registry.load_all()
    kept, idle = registry.ready("kept"), registry.ready("idle")
    registry.delete("idle")
    assert idle.map._file is None  # no request used it: closed at once
    query = ext.describe(make_scan(3, 7))
    with registry.using("doomed") as doomed, registry.using("doomed") as again:  # two requests in flight
        registry.delete("doomed")
        assert not (maps_dir / "doomed.h5").exists()
        with pytest.raises(NotFoundError):
            with registry.using("doomed"):
                pass
        assert doomed.localize(query).status == "localized"  # reads keyframes from the (unlinked) file
        assert doomed.map._file is not None
    assert again is doomed and doomed.map._file is None  # closed when the last request was done with it
    registry.close()
    assert kept.map._file is None and registry.entries() == []


def test_pose_uncertainty_turns_the_heading_into_degrees() -> None:
    """The API's covariance is the library's (x m, y m, yaw rad) with the heading's row and column in degrees."""
    import math

    import numpy as np

    from service.api.schemas import PoseUncertainty

    cov = np.array([[1.0, 0.1, 0.01], [0.1, 2.0, 0.02], [0.01, 0.02, 1e-4]])
    u = PoseUncertainty.from_array(cov)
    d = math.degrees(1.0)
    assert u.covariance[0][2] == pytest.approx(0.01 * d) and u.covariance[2][0] == pytest.approx(0.01 * d)  # 0.573
    assert u.covariance[1][2] == pytest.approx(0.02 * d)
    assert u.covariance[2][2] == pytest.approx(1e-4 * d * d)  # 0.3283 deg^2
    assert u.covariance[0][1] == pytest.approx(0.1) and u.covariance[1][1] == pytest.approx(2.0)
    assert (u.sigma_x_m, u.sigma_y_m) == (pytest.approx(1.0), pytest.approx(math.sqrt(2.0)))
    assert u.sigma_yaw_deg == pytest.approx(0.01 * d)  # 0.573 deg


def test_scan_layouts_are_checked_from_the_headers_before_the_build(tmp_path: Path) -> None:
    """QA session 40: a scan of another radar's layout failed the build only when the build reached it. One
    layout across PNG and .npy passes (a PNG's 11 metadata columns are not range bins); two layouts, or a
    member with no scan header, are refused naming them; the layout's first scan is decoded as the build will."""
    from service_test_fakes import make_scan

    from reradar_core.errors import ScanFormatError
    from reradar_core.io.scan import encode_navtech_png_bytes
    from service.core.archive import check_scan_layouts

    png = tmp_path / "1000.png"
    png.write_bytes(encode_navtech_png_bytes(make_scan(1, 1000)))
    npy = tmp_path / "2000.npy"
    np.save(npy, np.zeros((400, 3360), np.float32))
    other = tmp_path / "3000.npy"
    np.save(other, np.zeros((400, 3768), np.float32))
    broken = tmp_path / "4000.npy"
    broken.write_bytes(b"\x93NUMPY garbage")
    decoded: list[str] = []
    check_scan_layouts([png, npy], lambda p: decoded.append(p.name))  # type: ignore[func-returns-value]
    assert decoded == ["1000.png"]
    with pytest.raises(ScanFormatError, match=r"^the archive holds scans of 2 radar layouts: 2 of 400 azimuths x 3360 "
                                              r"range bins \(e\.g\. 1000\.png\) and 1 of 400 x 3768 \(e\.g\. 3000\.npy\)"):
        check_scan_layouts([png, npy, other])
    with pytest.raises(ScanFormatError, match=r"^scan archive member 4000\.npy: "):
        check_scan_layouts([png, broken])
    with pytest.raises(ScanFormatError, match=r"^scan archive member 1000\.png: unreadable$"):
        check_scan_layouts([png], lambda p: f"{p.name}: unreadable")
