"""One process without Redis follows its maps folder (QA session 40: a map rebuilt in place with `reradar build-map
--out <maps>/<id>.h5 --overwrite` kept being served in its old version until the service restarted; a map copied in
by hand was not served until then either)."""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path
from typing import Any

from maps.build import build_map

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import (  # noqa: E402
    API_KEY,
    FakeExtractor,
    keyframe_poses,
    keyframe_time,
    make_scan,
    started_app,
    upload_map_file,
)

AUTH = {"X-API-Key": API_KEY}


def _wait(client: Any, map_id: str, check: Any, timeout_s: float = 10.0) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        r = client.get(f"/maps/{map_id}", headers=AUTH)
        if check(r):
            return r
        assert time.monotonic() < deadline, r.text
        time.sleep(0.05)


def test_a_map_copied_in_rebuilt_in_place_or_removed_by_hand_is_followed(fake_map: Path, tmp_path: Path) -> None:
    maps_dir = tmp_path / "maps"
    with started_app(maps_dir, map_sync_interval_s=0.2) as client:
        assert client.get("/maps/route", headers=AUTH).status_code == 404
        shutil.copy(fake_map, maps_dir / "route.h5")  # copied in by hand while serving
        first = _wait(client, "route", lambda r: r.status_code == 200).json()
        assert first["state"] == "ready" and first["num_keyframes"] == len(keyframe_poses())
        # rebuilt in place, as `reradar build-map --out maps/route.h5 --overwrite` does (another file renamed over)
        n = 4
        build_map(maps_dir / "route.h5", FakeExtractor(), lambda i: make_scan(50 + i, keyframe_time(i)),
                  keyframe_poses()[:n], radar_preset="boreas", name="route", batch_size=4, overwrite=True)
        rebuilt = _wait(client, "route", lambda r: r.status_code == 200 and r.json()["num_keyframes"] == n).json()
        assert rebuilt["state"] == "ready"
        (maps_dir / "route.h5").unlink()  # removed by hand
        _wait(client, "route", lambda r: r.status_code == 404)


def test_a_delete_through_the_api_is_not_undone_by_the_folder_pass(fake_map: Path, tmp_path: Path) -> None:
    """The entry and its file go together under the registry's lock, so a folder pass in between cannot load the
    file again (it did for up to a pass in a fleet: ``adopt`` saw the file of an entry already removed)."""
    maps_dir = tmp_path / "maps"
    with started_app(maps_dir, map_sync_interval_s=0.01) as client:
        for cycle in range(10):
            shutil.copy(fake_map, maps_dir / f"m{cycle}.h5")
            _wait(client, f"m{cycle}", lambda r: r.status_code == 200)
            assert client.delete(f"/maps/m{cycle}", headers=AUTH).status_code == 200
            for _ in range(20):  # over several folder passes, from the moment the DELETE answered
                assert client.get(f"/maps/m{cycle}", headers=AUTH).status_code == 404
            assert not (maps_dir / f"m{cycle}.h5").exists()


def test_symbolic_links_in_the_maps_folder_neither_stop_the_pass_nor_lose_another_map(
        fake_map: Path, tmp_path: Path) -> None:
    """QA session 41: a link out of the maps folder (or a dangling one) stopped every folder pass (maps copied in
    later were never served), and DELETE of a link to another map deleted that map's file. A link is now the map's
    file as the link, as at start-up."""
    maps_dir = tmp_path / "maps"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    shutil.copy(fake_map, elsewhere / "shared.h5")
    with started_app(maps_dir, map_sync_interval_s=0.2) as client:
        (maps_dir / "dangling.h5").symlink_to(tmp_path / "nowhere" / "z.h5")
        (maps_dir / "outside.h5").symlink_to(elsewhere / "shared.h5")
        assert _wait(client, "outside", lambda r: r.status_code == 200).json()["state"] == "ready"
        shutil.copy(fake_map, maps_dir / "target.h5")  # the pass goes on after the links
        _wait(client, "target", lambda r: r.status_code == 200 and r.json()["state"] == "ready")
        (maps_dir / "alias.h5").symlink_to("target.h5")
        _wait(client, "alias", lambda r: r.status_code == 200 and r.json()["state"] == "ready")
        assert client.delete("/maps/alias", headers=AUTH).status_code == 200
        assert not (maps_dir / "alias.h5").is_symlink() and (maps_dir / "target.h5").is_file()
        assert client.delete("/maps/outside", headers=AUTH).status_code == 200
        assert (elsewhere / "shared.h5").is_file()  # the link went, not the file it pointed to
        time.sleep(0.6)  # passes over the remaining maps
        assert client.get("/maps/target", headers=AUTH).json()["state"] == "ready"
        assert client.get("/maps/alias", headers=AUTH).status_code == 404
        assert client.get("/maps/dangling", headers=AUTH).status_code == 404
        # the dangling link's name is taken all the same: a 409 that says why, not a build failing at its install
        r = upload_map_file(client, fake_map, "dangling")
        assert r.status_code == 409 and r.json()["detail"] == (
            "a broken symbolic link dangling.h5 (its target is gone) lies in the maps folder under this id: an "
            "operator must remove or repoint it, or pick another id"), r.text
        # a link whose target is removed is a map removed (it was still served)
        shutil.copy(fake_map, elsewhere / "gone.h5")
        (maps_dir / "gone.h5").symlink_to(elsewhere / "gone.h5")
        _wait(client, "gone", lambda r: r.status_code == 200 and r.json()["state"] == "ready")
        (elsewhere / "gone.h5").unlink()
        _wait(client, "gone", lambda r: r.status_code == 404)


def test_a_folder_pass_drops_only_the_entry_it_looked_at(fake_map: Path, tmp_path: Path) -> None:
    """Review (session 41): a pass that saw a map's file gone dropped whatever entry held the id by then, e.g. a build
    registered under it meanwhile."""
    from service.core.config import Settings
    from service.core.registry import MapRegistry

    reg = MapRegistry(Settings(maps_dir=tmp_path, load_demo_map=False), FakeExtractor())
    try:
        staged = reg.staging_dir() / "x.h5"
        shutil.copyfile(fake_map, staged)
        looked_at = reg.register_file("solo", staged)
        other = reg.get("solo")
        assert reg.forget("solo", expected=object()) is None  # type: ignore[arg-type]  # another entry: kept
        assert reg.get("solo") is other
        assert reg.forget("solo", expected=looked_at) is looked_at
        assert "solo" not in {e.map_id for e in reg.entries()}
    finally:
        reg.close()
