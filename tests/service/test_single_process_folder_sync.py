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
from service_test_fakes import API_KEY, FakeExtractor, keyframe_poses, keyframe_time, make_scan, started_app  # noqa: E402

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
