"""``DELETE /maps/{id}`` closes the map's files (QA): the HDF5 map and the shared arrays file (``.rrarr``, memory
mapped) stayed open for 30 s after a delete (a timer closed them then, whether or not a request used the map), so
each upload-and-delete cycle held two more file descriptors and the deleted file's disk space for that long. A map
let go of is now closed as soon as no request is using it (``MapRegistry.using``), and a localization in flight on
it finishes on the open files and closes them when it is done.
"""

from __future__ import annotations

import os
import sys
import threading
from pathlib import Path
from typing import Any

import pytest

from maps.database import MapDatabase
from reradar_core.io.scan import encode_navtech_png_bytes

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_test_fakes import (  # noqa: E402
    API_KEY,
    keyframe_time,
    make_scan,
    started_app,
    upload_map_file,
)

AUTH = {"X-API-Key": API_KEY}


def _open_files_under(folder: Path) -> list[str]:
    """The files under ``folder`` this process holds a descriptor of (deleted ones too: ``... (deleted)``)."""
    root = str(folder.resolve())
    held = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:  # closed since the listing
            continue
        if target.startswith(root):
            held.append(target)
    return held


pytestmark = pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc/self/fd")


def test_upload_and_delete_cycles_leave_no_file_open(fake_map: Path, tmp_path: Path) -> None:
    maps_dir = tmp_path / "maps"
    with started_app(maps_dir) as client:
        before = len(os.listdir("/proc/self/fd"))
        for cycle in range(5):
            r = upload_map_file(client, fake_map, f"cycle-{cycle}")
            assert r.status_code == 201, r.text
            held = _open_files_under(maps_dir)
            assert any(f.endswith(".h5") or ".h5 " in f for f in held), held  # the map is served from its files
            assert any(".rrarr" in f for f in held), held
            r = client.delete(f"/maps/cycle-{cycle}", headers=AUTH)
            assert r.status_code == 200, r.text
            assert _open_files_under(maps_dir) == []  # at once, not after a grace period
        # nothing else piles up per cycle either (a little slack for the test client's own threads)
        assert len(os.listdir("/proc/self/fd")) <= before + 2


def test_a_localization_in_flight_finishes_on_a_deleted_map_which_closes_after_it(
        fake_map: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Keyframes read from the HDF5 file during the request (no shared arrays, no preload), so a map closed under
    the request would fail it ("map is closed")."""
    maps_dir = tmp_path / "maps"
    in_flight, deleted = threading.Event(), threading.Event()
    localize = MapDatabase.localize

    def paused_localize(self: MapDatabase, *args: Any, **kwargs: Any) -> Any:
        in_flight.set()
        assert deleted.wait(30)
        return localize(self, *args, **kwargs)

    monkeypatch.setattr(MapDatabase, "localize", paused_localize)
    answers: list[Any] = []
    with started_app(maps_dir, share_map_arrays=False, preload_keyframes=False, keyframe_cache_size=1) as client:
        r = upload_map_file(client, fake_map, "doomed")
        assert r.status_code == 201, r.text
        db = client.app.state.reradar.registry.ready("doomed")  # type: ignore[attr-defined]
        png = encode_navtech_png_bytes(make_scan(3, keyframe_time(3)))
        request = threading.Thread(target=lambda: answers.append(client.post(
            "/localize", data={"map_id": "doomed"}, files={"scan": ("s.png", png)}, headers=AUTH)))
        request.start()
        try:
            assert in_flight.wait(30)
            r = client.delete("/maps/doomed", headers=AUTH)
            assert r.status_code == 200, r.text
            assert not (maps_dir / "doomed.h5").exists()
            assert db.map._file is not None  # still open for the request using it
            assert client.get("/maps/doomed", headers=AUTH).status_code == 404
        finally:
            deleted.set()
            request.join(60)
        assert answers and answers[0].status_code == 200, answers and answers[0].text
        assert answers[0].json()["status"] == "localized"
        assert db.map._file is None  # closed when the request was done with it
        assert _open_files_under(maps_dir) == []
        # a request for the deleted map now is a 404, not a closed file
        r = client.post("/localize", data={"map_id": "doomed"}, files={"scan": ("s.png", png)}, headers=AUTH)
        assert r.status_code == 404, r.text
