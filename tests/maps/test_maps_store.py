"""HDF5 map store: round trip, dtypes, atomic writes, schema and model checks."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from maps.store import (
    MAX_KEYPOINT_RANGE_M,
    POSE_TIME_FIRST_AZIMUTH,
    POSE_TIME_MID_SWEEP,
    SCHEMA_VERSION,
    MapMetadata,
    MapWriter,
    check_model,
    open_map,
    read_metadata,
    write_map,
)
from reradar_core.errors import MapFormatError, ModelMismatchError
from reradar_core.features import ScanFeatures

D, C = 16, 8


def _meta(**kw: object) -> MapMetadata:
    base = dict(model_id="test-model", weights_sha256="a" * 64, radar_preset="boreas", cartesian_width_px=201,
                cartesian_resolution_m=0.64, descriptor_dim=D, local_descriptor_dim=C, source="unit test",
                name="t")
    base.update(kw)
    return MapMetadata(**base)  # type: ignore[arg-type]


def _features(rng: np.random.Generator, n: int) -> list[ScanFeatures]:
    out = []
    for i in range(n):
        k = int(rng.integers(0, 30))
        g = rng.normal(size=D)
        loc = rng.normal(size=(k, C))
        loc /= np.maximum(np.linalg.norm(loc, axis=1, keepdims=True), 1e-9)
        out.append(ScanFeatures(g / np.linalg.norm(g), rng.uniform(-80, 80, (k, 2)), loc, 1_000_000 + i * 250_000))
    return out


def test_round_trip_preserves_values_and_dtypes(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    feats = _features(rng, 7)
    # poses far from the origin with sub-millimetre detail: float16/float32 would lose them
    poses = np.column_stack([6.2e5 + rng.uniform(0, 1, 7), 4.8e6 + rng.uniform(0, 1, 7), rng.uniform(-3, 3, 7)])
    path = write_map(tmp_path / "m.h5", _meta(), feats, poses)
    with open_map(path, "test-model", "a" * 64) as m:
        assert len(m) == 7 and m.metadata.schema_version == SCHEMA_VERSION
        assert m.metadata.num_keyframes == 7 and m.metadata.created_utc.endswith("Z")
        assert m.poses.dtype == np.float64
        np.testing.assert_array_equal(m.poses, poses)
        np.testing.assert_array_equal(m.timestamps_us, [f.timestamp_us for f in feats])
        np.testing.assert_allclose(m.global_descriptors, np.stack([f.global_descriptor for f in feats]), atol=0)
        for i in (0, 3, 6):
            kf = m.read_keyframe(i)
            np.testing.assert_array_equal(kf.keypoints_xy_m, feats[i].keypoints_xy_m)
            assert kf.local_descriptors.dtype == np.float16
            np.testing.assert_array_equal(kf.local_descriptors, feats[i].local_descriptors)
        with pytest.raises(IndexError):
            m.read_keyframe(7)
    with h5py.File(path) as f:
        assert f["poses"].dtype == np.float64 and f["global_descriptors"].dtype == np.float32
        assert f["keyframes/000002/local_descriptors"].dtype == np.float16


def test_crash_mid_write_leaves_no_map_and_keeps_old_one(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    path = write_map(tmp_path / "m.h5", _meta(), _features(rng, 3), np.zeros((3, 3)))
    before = path.read_bytes()
    with pytest.raises(RuntimeError, match="boom"):
        with MapWriter(path, _meta(), overwrite=True) as w:
            for f in _features(rng, 5):
                w.add(f, np.zeros(3))
            raise RuntimeError("boom")
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["m.h5"]  # no temporary left behind
    new = tmp_path / "new.h5"
    with pytest.raises(RuntimeError):
        with MapWriter(new, _meta()) as w:
            w.add(_features(rng, 1)[0], np.zeros(3))
            raise RuntimeError("crash")
    assert not new.exists()


def test_refuses_existing_without_overwrite_and_bad_keyframes(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    path = write_map(tmp_path / "m.h5", _meta(), _features(rng, 1), np.zeros((1, 3)))
    with pytest.raises(FileExistsError):
        MapWriter(path, _meta())
    with pytest.raises(ValueError, match="pose"):
        with MapWriter(tmp_path / "x.h5", _meta()) as w:
            w.add(_features(rng, 1)[0], np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="global descriptor"):
        with MapWriter(tmp_path / "y.h5", _meta(descriptor_dim=D + 1)) as w:
            w.add(_features(rng, 1)[0], np.zeros(3))
    assert not (tmp_path / "x.h5").exists() and not (tmp_path / "y.h5").exists()


def test_model_mismatch_is_refused(tmp_path: Path) -> None:
    path = write_map(tmp_path / "m.h5", _meta(), _features(np.random.default_rng(3), 2), np.zeros((2, 3)))
    with pytest.raises(ModelMismatchError, match="rebuild the map"):
        open_map(path, "other-model", "b" * 64)
    check_model(read_metadata(path), "test-model", "a" * 64)  # same hash: accepted
    check_model(read_metadata(path), "?", "a" * 64)  # same hash, model id not given: accepted


def test_a_map_of_the_same_weights_described_another_way_is_refused(tmp_path: Path) -> None:
    """The same weights with the canonical heading (model id ``...-ch``) describe scans differently: a map described
    without it is refused, with a message saying why and what to do."""
    path = write_map(tmp_path / "m.h5", _meta(), _features(np.random.default_rng(3), 2), np.zeros((2, 3)))
    with pytest.raises(ModelMismatchError, match="test-model-ch.*rebuild the map"):
        open_map(path, "test-model-ch", "a" * 64)
    with open_map(path, "test-model", "a" * 64) as kf_map:
        assert kf_map.metadata.model_id == "test-model"
    # the image size alone (the far view's -in257) is left to the service's image check, which names the images
    check_model(read_metadata(path), "test-model-in257", "a" * 64)
    with pytest.raises(ModelMismatchError, match="canonical heading"):
        check_model(read_metadata(path), "test-model-in257-ch", "a" * 64)


def test_bad_files_raise_map_format_error(tmp_path: Path) -> None:
    garbage = tmp_path / "garbage.h5"
    garbage.write_bytes(b"not an hdf5 file at all")
    with pytest.raises(MapFormatError, match="not a readable HDF5"):
        open_map(garbage)
    with pytest.raises(MapFormatError, match="no such map"):
        open_map(tmp_path / "missing.h5")
    empty = tmp_path / "empty.h5"
    with h5py.File(empty, "w"):
        pass
    with pytest.raises(MapFormatError, match="schema_version"):
        open_map(empty)
    path = write_map(tmp_path / "v.h5", _meta(), _features(np.random.default_rng(4), 2), np.zeros((2, 3)))
    with h5py.File(path, "r+") as f:
        f.attrs["schema_version"] = 99
    with pytest.raises(MapFormatError, match="schema_version 99"):
        open_map(path)
    path = write_map(tmp_path / "p.h5", _meta(), _features(np.random.default_rng(5), 2), np.zeros((2, 3)))
    with h5py.File(path, "r+") as f:
        del f["poses"]
        f.create_dataset("poses", data=np.zeros((2, 3), np.float16))
    with pytest.raises(MapFormatError, match="float64"):
        open_map(path)


def test_links_and_external_storage_are_refused(tmp_path: Path) -> None:
    secret = tmp_path / "secret.bin"
    secret.write_bytes(np.arange(6, dtype=np.float64).tobytes())
    path = write_map(tmp_path / "x.h5", _meta(), _features(np.random.default_rng(6), 2), np.zeros((2, 3)))
    with h5py.File(path, "r+") as f:  # poses read from another file through external raw storage
        del f["poses"]
        f.create_dataset("poses", shape=(2, 3), dtype=np.float64, external=[(str(secret), 0, 48)])
    with pytest.raises(MapFormatError, match="external"):
        open_map(path)
    other = write_map(tmp_path / "o.h5", _meta(), _features(np.random.default_rng(7), 2), np.zeros((2, 3)))
    path = write_map(tmp_path / "y.h5", _meta(), _features(np.random.default_rng(8), 2), np.zeros((2, 3)))
    with h5py.File(path, "r+") as f:
        del f["global_descriptors"]
        f["global_descriptors"] = h5py.ExternalLink(str(other), "/global_descriptors")
    with pytest.raises(MapFormatError, match="link"):
        open_map(path)
    path = write_map(tmp_path / "z.h5", _meta(), _features(np.random.default_rng(9), 2), np.zeros((2, 3)))
    with h5py.File(path, "r+") as f:
        del f["keyframes/000001"]
        f["keyframes/000001"] = h5py.ExternalLink(str(other), "/keyframes/000000")
    with pytest.raises(MapFormatError, match="'/keyframes/000001' is an external link"):
        open_map(path)  # refused at open, before any keyframe is read


def test_pose_time_is_recorded_and_old_maps_are_flagged(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    rng = np.random.default_rng(3)
    path = write_map(tmp_path / "m.h5", _meta(), _features(rng, 3), np.zeros((3, 3)))
    assert read_metadata(path).pose_time == POSE_TIME_MID_SWEEP
    with h5py.File(path, "a") as f:  # a map written before the attribute existed
        del f.attrs["pose_time"]
    with caplog.at_level("WARNING", logger="maps.store"):
        assert read_metadata(path).pose_time == POSE_TIME_FIRST_AZIMUTH
    assert "first-azimuth" in caplog.text and "rebuild" in caplog.text
    with h5py.File(path, "a") as f:
        f.attrs["pose_time"] = "noon"
    with pytest.raises(MapFormatError, match="pose_time"):
        read_metadata(path)


def test_links_anywhere_are_refused_without_following_them(tmp_path: Path) -> None:
    """A link the reader never reads (an extra member) still makes the map refused: soft, external, and in a
    keyframe group or at the root; the external target is never opened (it does not exist)."""
    cases = {
        "keyframes/000001/ext": h5py.ExternalLink("/nonexistent/secret.h5", "/x"),
        "alias": h5py.SoftLink("/poses"),
        "keyframes/000000/dangling": h5py.SoftLink("/no/such/object"),
    }
    for i, (name, link) in enumerate(cases.items()):
        path = write_map(tmp_path / f"l{i}.h5", _meta(), _features(np.random.default_rng(20 + i), 2), np.zeros((2, 3)))
        with h5py.File(path, "r+") as f:
            f[name] = link
        kind = "an external link" if isinstance(link, h5py.ExternalLink) else "a soft link"
        with pytest.raises(MapFormatError, match=f"'/{name}' is {kind}"):
            open_map(path)


def _map_with(tmp_path: Path, name: str, edit) -> Path:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(30)
    feats = [ScanFeatures(f.global_descriptor, rng.uniform(-80, 80, (5, 2)), rng.normal(size=(5, C)), f.timestamp_us)
             for f in _features(rng, 3)]
    path = write_map(tmp_path / f"{name}.h5", _meta(), feats, np.zeros((3, 3)))
    with h5py.File(path, "r+") as f:
        edit(f)
    return path


def test_keypoints_must_be_finite_and_within_the_radar_range(tmp_path: Path) -> None:
    # the longest preset range (Boreas: -0.31 m + 3,359 bins x 0.0596 m = 199.886 m) plus the 50 m margin
    assert MAX_KEYPOINT_RANGE_M == pytest.approx(249.886, abs=1e-3)

    def set_kp(value: float, row: int = 0, col: int = 0):  # type: ignore[no-untyped-def]
        def edit(f: h5py.File) -> None:
            f["keyframes/000001/keypoints_xy_m"][row, col] = value
        return edit

    for name, value, match in (("nan", np.nan, "finite"), ("inf", np.inf, "finite"),
                               ("huge", 1e30, "within the radar's range"),
                               ("far", 2500.0, r"lies 250\d m from the sensor")):
        with open_map(_map_with(tmp_path, name, set_kp(value))) as m:
            m.read_keyframe(0)
            with pytest.raises(MapFormatError, match=match):
                m.read_keyframe(1)
    # the bound is a distance from the sensor: (200, 100) is 223.6 m (kept), (200, 160) is 256.1 m (refused)
    def set_xy(x: float, y: float):  # type: ignore[no-untyped-def]
        def edit(f: h5py.File) -> None:
            f["keyframes/000002/keypoints_xy_m"][0] = (x, y)
        return edit

    with open_map(_map_with(tmp_path, "near", set_xy(200.0, 100.0))) as m:
        np.testing.assert_array_equal(m.read_keyframe(2).keypoints_xy_m[0], [200.0, 100.0])
    with open_map(_map_with(tmp_path, "edge", set_xy(200.0, 160.0))) as m, pytest.raises(MapFormatError, match="256"):
        m.read_keyframe(2)

    def nan_desc(f: h5py.File) -> None:
        f["keyframes/000000/local_descriptors"][2, 3] = np.nan

    with open_map(_map_with(tmp_path, "desc", nan_desc)) as m, pytest.raises(MapFormatError, match="local_descriptors"):
        m.read_keyframe(0)


def test_keyframe_poses_beyond_the_coordinate_bound_are_refused(tmp_path: Path) -> None:
    def far_pose(f: h5py.File) -> None:
        f["poses"][1, 0] = 1e300

    with pytest.raises(MapFormatError, match="within"):
        open_map(_map_with(tmp_path, "pose", far_pose))


def test_shipped_demo_map_passes_every_check() -> None:
    """The demo map (built by `scripts/build_demo_map.py` through `maps.build.build_map`, as `reradar
    build-map` builds) opens and every keyframe reads through the validation."""
    from maps.paths import DEMO_MAP_PATH
    from reradar_core.localization import LocalizationConfig, repetition_settings

    with open_map(DEMO_MAP_PATH) as m:
        assert len(m) > 0
        # its place repetition is stored, under the shipped settings (rebuild the demo when they change)
        assert m.place_repetition is not None
        assert m.place_repetition.settings == repetition_settings(LocalizationConfig())
        for i in range(len(m)):
            kf = m.read_keyframe(i)
            assert np.all(np.isfinite(kf.keypoints_xy_m))
            assert float(np.max(np.hypot(*kf.keypoints_xy_m.T.astype(np.float64)))) <= MAX_KEYPOINT_RANGE_M


def test_a_stored_place_repetition_round_trips_and_a_damaged_one_is_refused(tmp_path: Path) -> None:
    from reradar_core.localization import RepetitionTable

    rng = np.random.default_rng(40)
    feats = _features(rng, 3)
    table = RepetitionTable('[{"k":1}]', np.array([0.9, 0.8, 0.0]), np.array([0.0, 0.85, 0.0]), np.array([-1, 0, -1]))
    with MapWriter(tmp_path / "r.h5", _meta()) as w:
        for f in feats:
            w.add(f, np.zeros(3))
        with pytest.raises(ValueError, match="2 rows for 3 keyframes"):
            w.set_place_repetition(RepetitionTable("{}", np.ones(2), np.zeros(2), np.full(2, -1)))
        w.set_place_repetition(table)
        back = w.read_keyframe(1)  # as stored: float16 descriptors
        np.testing.assert_array_equal(back.local_descriptors, feats[1].local_descriptors.astype(np.float16))
    with open_map(tmp_path / "r.h5") as m:
        got = m.place_repetition
        assert got is not None and got.settings == table.settings and got.at(1) == table.at(1)
        np.testing.assert_array_equal(got.rival_keyframe_id, [-1, 0, -1])
    with open_map(write_map(tmp_path / "plain.h5", _meta(), feats, np.zeros((3, 3)))) as m:
        assert m.place_repetition is None  # optional: maps built before session 28, or with --no-place-repetition

    def with_table(edit):  # type: ignore[no-untyped-def]
        def add(f: h5py.File) -> None:
            g = f.create_group("place_repetition")
            g.create_dataset("neighbour_score", data=np.array([0.9, 0.8, 0.7]))
            g.create_dataset("rival_score", data=np.zeros(3))
            g.create_dataset("rival_keyframe_id", data=np.full(3, -1, np.int64))
            g.attrs["settings"] = "[]"
            edit(g)
        return add

    def put(name: str, data: object):  # type: ignore[no-untyped-def]
        def edit(g: h5py.Group) -> None:
            del g[name]
            g.create_dataset(name, data=data)
        return edit

    def no_settings(g: h5py.Group) -> None:
        del g.attrs["settings"]

    def long_settings(g: h5py.Group) -> None:
        g.attrs["settings"] = "x" * 20_000

    def missing(g: h5py.Group) -> None:
        del g["rival_score"]

    def number_settings(g: h5py.Group) -> None:
        g.attrs["settings"] = 5

    def array_settings(g: h5py.Group) -> None:
        g.attrs["settings"] = np.array(["a", "b", "c"], dtype=object)

    for name, edit, match in (("short", put("neighbour_score", np.ones(2)), r"shape \(2,\)"),
                              ("above1", put("neighbour_score", np.array([0.9, 1.5, 0.7])), r"\[0, 1\]"),
                              ("nan", put("rival_score", np.array([np.nan, 0, 0])), r"\[0, 1\]"),
                              ("floatid", put("rival_keyframe_id", np.zeros(3)), "an integer dtype"),
                              ("badid", put("rival_keyframe_id", np.array([5, -1, -1])), r"\[-1, 3\)"),
                              ("nosettings", no_settings, "no 'settings'"), ("long", long_settings, "16384"),
                              ("missing", missing, "rival_score"),
                              ("number", number_settings, "'settings' must be text"),
                              ("array", array_settings, "'/place_repetition' attribute 'settings' must be a single")):
        with pytest.raises(MapFormatError, match=match):
            open_map(_map_with(tmp_path, f"rep-{name}", with_table(edit)))

    def not_a_group(f: h5py.File) -> None:
        f.create_dataset("place_repetition", data=np.zeros(3))

    with pytest.raises(MapFormatError, match="must be a group"):
        open_map(_map_with(tmp_path, "rep-dataset", not_a_group))


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc, where no file can be created")
def test_a_map_that_cannot_be_created_says_why_in_words_without_the_temporary_name(tmp_path: Path) -> None:
    """QA session 40: `build-map --out /proc/x.h5` ended in HDF5's "unable to synchronously create file" naming the
    writer's hidden temporary file."""
    with pytest.raises(OSError) as info, MapWriter(Path("/proc/x.h5"), _meta()):
        pass
    assert info.value.strerror == "cannot create the map file x.h5 there: No such file or directory"
    assert ".tmp" not in str(info.value)
