"""Shared map arrays (``maps.arrays``): the same keyframes and answers as the HDF5 map, one file mapped by
several processes, a changed map gets a new file, a truncated / corrupt / foreign file is rebuilt and never
served, and concurrent builders leave one complete file."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from maps.arrays import SUFFIX, MapArrays, prune_arrays
from maps.database import MapDatabase
from maps.store import MapMetadata, open_map, write_map
from reradar_core.features import ScanFeatures
from reradar_core.localization import LocalizationConfig
from reradar_core.localization.screening import screen_keyframe
from reradar_core.matching import AlignmentConfig

REPO = Path(__file__).resolve().parents[2]
D, C = 16, 8


def _meta() -> MapMetadata:
    return MapMetadata(model_id="test-model", weights_sha256="a" * 64, radar_preset="boreas",
                       cartesian_width_px=201, cartesian_resolution_m=0.64, descriptor_dim=D,
                       local_descriptor_dim=C, source="unit test", name="t")


def _world(seed: int, n_keyframes: int = 12) -> tuple[list[ScanFeatures], np.ndarray, np.ndarray]:
    """Keyframes along a line through a field of landmarks with descriptors tied to the landmark, so
    queries localize; one keyframe has fewer landmarks than the screen's pair count (the odd path)."""
    rng = np.random.default_rng(seed)
    world = rng.uniform(-150, 150, (900, 2))
    wdesc = rng.normal(size=(900, C))
    wdesc /= np.linalg.norm(wdesc, axis=1, keepdims=True)
    poses = np.column_stack([np.linspace(-60, 60, n_keyframes), rng.uniform(-3, 3, n_keyframes),
                             rng.uniform(-np.pi, np.pi, n_keyframes)])
    feats = []
    for i, (x, y, yaw) in enumerate(poses):
        c, s = np.cos(yaw), np.sin(yaw)
        local = (world - [x, y]) @ np.array([[c, -s], [s, c]])
        keep = np.flatnonzero(np.hypot(*local.T) < 60)[: 3 if i == 5 else 200]
        g = rng.normal(size=D)
        feats.append(ScanFeatures(g / np.linalg.norm(g), local[keep], wdesc[keep], 1_000_000 + i))
    return feats, poses, world


@pytest.fixture()
def map_path(tmp_path: Path) -> Path:
    feats, poses, _ = _world(0)
    return write_map(tmp_path / "m.h5", _meta(), feats, poses)


def _files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.name.endswith(SUFFIX))


def test_arrays_hold_the_maps_keyframes_and_screen_data(map_path: Path, tmp_path: Path) -> None:
    config = AlignmentConfig()
    with open_map(map_path) as m:
        arrays = MapArrays.open_or_build(m, tmp_path / "arrays", config)
        assert len(arrays) == len(m)
        np.testing.assert_array_equal(arrays.poses, m.poses)
        np.testing.assert_array_equal(arrays.timestamps_us, m.timestamps_us)
        assert m.global_descriptors is not None
        np.testing.assert_array_equal(arrays.global_descriptors, m.global_descriptors)
        for i in range(len(m)):
            want, got = m.read_keyframe(i), arrays.read_keyframe(i)
            np.testing.assert_array_equal(got.keypoints_xy_m, want.keypoints_xy_m)
            np.testing.assert_array_equal(got.local_descriptors, want.local_descriptors)
            assert got.keypoints_xy_m.dtype == np.float32 and got.local_descriptors.dtype == np.float16
            assert not got.keypoints_xy_m.flags.writeable  # views of a read-only mapping, not copies
            screen, ref = arrays.read_screen(i, config), screen_keyframe(want.keypoints_xy_m,
                                                                         want.local_descriptors, config)
            assert screen is not None
            np.testing.assert_array_equal(screen.grid.packed, ref.grid.packed)
            assert (screen.grid.n, screen.grid.origin_m, screen.grid.cell_m) == (ref.grid.n, ref.grid.origin_m,
                                                                                 ref.grid.cell_m)
        # other screen settings: the stored masks do not apply, the caller builds its own
        assert arrays.read_screen(0, AlignmentConfig(score_threshold_m=1.0)) is None
        with pytest.raises(IndexError):
            arrays.read_keyframe(len(m))


def test_localization_is_the_same_with_and_without_shared_arrays(map_path: Path, tmp_path: Path) -> None:
    feats, poses, _ = _world(0)
    config = LocalizationConfig(top_k=4, verify_k=2, max_candidates=8)
    private = MapDatabase(open_map(map_path), keyframe_cache_size=None, config=config, preload=True)
    shared = MapDatabase(open_map(map_path), keyframe_cache_size=None, config=config, preload=True,
                         arrays_dir=tmp_path / "arrays")
    assert shared.arrays is not None and private.arrays is None
    localized = 0
    for i in range(len(feats)):
        q = ScanFeatures(feats[i].global_descriptor, feats[i].keypoints_xy_m + np.float32(0.3),
                         feats[i].local_descriptors)
        a, b = private.localize(q), shared.localize(q)
        assert (a.status, a.reason) == (b.status, b.reason)
        assert [(v.keyframe_id, v.screen_score, v.num_inliers) for v in a.candidates] == \
               [(v.keyframe_id, v.screen_score, v.num_inliers) for v in b.candidates]
        if a.T_map_query is not None:
            np.testing.assert_array_equal(a.T_map_query, b.T_map_query)
            localized += 1
    assert localized >= len(feats) // 2
    private.close()
    shared.close()


_CHILD = textwrap.dedent("""
    import json, os, sys
    from maps.database import MapDatabase
    from maps.store import open_map
    db = MapDatabase(open_map(sys.argv[1]), keyframe_cache_size=None, preload=True, arrays_dir=sys.argv[2])
    mapped = sorted({line.split()[-1] for line in open("/proc/self/maps") if line.rstrip().endswith(".rrarr")})
    st = os.stat(db.arrays.path)
    print(json.dumps({"mapped": mapped, "inode": st.st_ino, "first": float(db.arrays.poses[0, 0]),
                      "n": len(db), "kp": db.localizer.keyframes.read_keyframe(3).keypoints_xy_m.tolist()}))
""")


def test_two_processes_map_one_file_built_once(map_path: Path, tmp_path: Path) -> None:
    arrays_dir = tmp_path / "arrays"
    env = {**os.environ, "PYTHONPATH": str(REPO), "OPENBLAS_NUM_THREADS": "1"}
    # started together: they race to build the file; the lock makes one build it and the other map it
    procs = [subprocess.Popen([sys.executable, "-c", _CHILD, str(map_path), str(arrays_dir)], cwd=REPO, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    outs = []
    for p in procs:
        out, err = p.communicate(timeout=300)
        assert p.returncode == 0, err
        outs.append(json.loads(out.strip().splitlines()[-1]))
    files = _files(arrays_dir)
    assert len(files) == 1, files
    assert not [p for p in arrays_dir.iterdir() if p.name.endswith(".tmp")]
    assert outs[0]["mapped"] == outs[1]["mapped"] == [str(files[0])]
    assert outs[0]["inode"] == outs[1]["inode"] == files[0].stat().st_ino
    assert outs[0]["kp"] == outs[1]["kp"] and outs[0]["n"] == outs[1]["n"] == 12


def test_a_changed_map_gets_new_arrays_and_old_mappings_stay_valid(map_path: Path, tmp_path: Path) -> None:
    arrays_dir = tmp_path / "arrays"
    old_map = open_map(map_path)
    old = MapArrays.open_or_build(old_map, arrays_dir)
    old_kp = old.read_keyframe(2).keypoints_xy_m.copy()
    feats, poses, _ = _world(1)  # a map update installed over the same file name while serving
    write_map(map_path, _meta(), feats, poses, overwrite=True)
    with open_map(map_path) as m:
        new = MapArrays.open_or_build(m, arrays_dir)
    assert new.path != old.path and len(_files(arrays_dir)) == 2
    np.testing.assert_array_equal(new.poses, poses)
    np.testing.assert_array_equal(new.read_keyframe(2).keypoints_xy_m, feats[2].keypoints_xy_m)
    # the process still serving the old version reads its old data, unchanged
    np.testing.assert_array_equal(old.read_keyframe(2).keypoints_xy_m, old_kp)
    # the old file is pruned once unused (its mapping stays valid after the unlink)
    live = arrays_dir / f".{new.path.name}.{os.getpid()}.1.tmp"  # a writer still running: kept
    live.touch()
    (arrays_dir / f".{old.path.name}.lock").touch()
    (arrays_dir / f".{new.path.name}.lock").touch()
    removed = prune_arrays(arrays_dir, keep=[new.path.name], min_age_s=0)
    assert sorted(p.name for p in removed) == sorted([old.path.name, f".{old.path.name}.lock"])
    assert _files(arrays_dir) == [new.path] and (arrays_dir / f".{new.path.name}.lock").exists() and live.exists()
    np.testing.assert_array_equal(old.read_keyframe(2).keypoints_xy_m, old_kp)
    old_map.close()


def _damage_truncate(p: Path) -> None:
    with open(p, "r+b") as fh:
        fh.truncate(p.stat().st_size - 100)


def _damage_flip(p: Path) -> None:
    data = bytearray(p.read_bytes())
    data[-200] ^= 0x40  # inside the payload (the local descriptors): only the checksum can tell
    p.write_bytes(bytes(data))


def _damage_header(p: Path) -> None:
    data = bytearray(p.read_bytes())
    data[30:40] = b"\xff" * 10
    p.write_bytes(bytes(data))


def _damage_empty(p: Path) -> None:
    p.write_bytes(b"")


@pytest.mark.parametrize("damage", [_damage_truncate, _damage_flip, _damage_header, _damage_empty])
def test_a_damaged_arrays_file_is_rebuilt_not_served(map_path: Path, tmp_path: Path, damage,
                                                     caplog: pytest.LogCaptureFixture) -> None:
    arrays_dir = tmp_path / "arrays"
    with open_map(map_path) as m:
        path = MapArrays.open_or_build(m, arrays_dir).path
        good = path.read_bytes()
        damage(path)
        with caplog.at_level("WARNING", logger="maps.arrays"):
            again = MapArrays.open_or_build(m, arrays_dir)
        assert "rebuilding" in caplog.text
        assert again.path == path and path.read_bytes() == good
        np.testing.assert_array_equal(again.read_keyframe(4).keypoints_xy_m, m.read_keyframe(4).keypoints_xy_m)


def test_a_file_of_other_settings_under_the_name_is_rebuilt(map_path: Path, tmp_path: Path) -> None:
    arrays_dir = tmp_path / "arrays"
    with open_map(map_path) as m:
        a = MapArrays.open_or_build(m, arrays_dir, AlignmentConfig())
        b = MapArrays.open_or_build(m, arrays_dir, AlignmentConfig(grid_cell_m=0.25))
        assert a.path != b.path
        os.replace(b.path, a.path)  # a foreign file under the name: its key does not match, so it is rebuilt
        c = MapArrays.open_or_build(m, arrays_dir, AlignmentConfig())
        assert c.grid_cell_m == 0.5 and c.read_screen(0, AlignmentConfig()) is not None


def test_an_unwritable_arrays_dir_falls_back_to_private_reads(map_path: Path, tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("x")
    db = MapDatabase(open_map(map_path), keyframe_cache_size=None, preload=True, arrays_dir=blocker / "arrays")
    assert db.arrays is None and len(db) == 12
    db.close()
