"""Suites: the smoke suite renders in the real layout, resumes, re-renders identically; definitions are sane."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from reradar_core.errors import ConfigError, DatasetError
from reradar_core.io.datasets import load_sequence
from reradar_core.io.poses import PoseSequence, write_txyyaw_csv
from reradar_core.io.scan import read_navtech_png
from reradar_core.sim.suites import SUITES, build_suite, suite_profile
from reradar_core.sim.world import RoadNetwork, World
from reradar_core.sim.writer import COMPLETE_MARKER


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    return build_suite("smoke", root=tmp_path_factory.mktemp("smoke"), progress=False)


def test_smoke_suite_layout_and_poses(smoke):
    assert smoke.layout == "boreas" and smoke.preset == "boreas" and smoke.radius_m == 20.0
    assert len(smoke.database) == 1 and len(smoke.queries) == 1 and smoke.query_conditions == ["snow_cover"]
    db = load_sequence(smoke.database[0])  # the generic reader, no hints: layout + preset detected
    q = smoke.query_sequences()[0]
    assert db.layout == "boreas" and db.preset.name == "boreas"
    assert len(db) == 20 and len(q) == 20
    scan = db.load_scan(0)
    assert scan.power.shape == (400, 3360) and scan.timestamp_us == db.timestamps_us[0]
    # every query has a database scan within the recall radius (a place-recognition-ready split)
    d = np.linalg.norm(q.poses.xy[:, None] - db.poses.xy[None], axis=2).min(axis=1)
    assert np.all(d < smoke.radius_m)
    # and the query runs in another lane, not on the database poses
    assert np.all(d > 0.5)
    assert (smoke.root / "database" / COMPLETE_MARKER).is_file()


def test_smoke_suite_resumes_and_renders_identically(smoke, tmp_path):
    again = build_suite("smoke", root=smoke.root, progress=False)  # complete: nothing re-rendered
    assert again.database == smoke.database
    db = load_sequence(smoke.database[0])
    first = db.scan_paths[3]
    mtime = first.stat().st_mtime_ns
    build_suite("smoke", root=smoke.root, progress=False)
    assert first.stat().st_mtime_ns == mtime
    # an interrupted render (marker missing, one scan deleted) is completed, and the scan comes back identical
    ref = read_navtech_png(first, "boreas").power.copy()
    (smoke.root / "database" / COMPLETE_MARKER).unlink()
    first.unlink()
    build_suite("smoke", root=smoke.root, progress=False)
    np.testing.assert_array_equal(read_navtech_png(first, "boreas").power, ref)


def test_suite_definitions():
    for name in ("smoke", "boreas-sim", "loop-sim", "loop-sim-hard", "offroad-sim", "offroad-sim-hard",
                 "train-source",
                 "train-target-boreas",
                 "train-target-loop", "train-target-loop-open", "train-target-offroad"):
        assert name in SUITES
    # training splits never contain query sequences, evaluation suites always do
    for name, suite in SUITES.items():
        roles = {s.role for s in suite.sequences}
        if suite.purpose == "confidence":  # a split's look-alike / periodic sessions: no weights, no queries
            assert name.startswith("train-")
            assert roles == ({"database", "confidence"} if name.endswith("-periodic") else {"confidence"})
        elif name.startswith("train-"):
            assert roles <= {"train", "confidence"} and "train" in roles
        else:
            assert {"database", "query"} <= roles
    assert SUITES["offroad-sim"].radius_m == 25.0 and SUITES["boreas-sim"].radius_m == 20.0
    from reradar_core.sim.suites import suite_names

    assert suite_names("benchmark") == ["boreas-sim", "loop-sim", "loop-sim-hard", "offroad-sim",
                                           "offroad-sim-hard"]
    assert all(n.startswith("train-") for n in suite_names("training"))
    # every target split has a session that trains no weights, for the confidence and floor fit
    for name in ("train-target-boreas", "train-target-loop", "train-target-loop-open", "train-target-offroad"):
        assert any(s.role == "confidence" for s in SUITES[name].sequences)
        seeds = [s.traversal_seed for s in SUITES[name].sequences]
        assert len(seeds) == len(set(seeds))
    # the Boreas training traversal is never one of the query traversals
    q_seeds = {s.traversal_seed for s in SUITES["boreas-sim"].sequences}
    assert not q_seeds & {s.traversal_seed for s in SUITES["train-target-boreas"].sequences}
    # no training split drives a query traversal (same world and traversal seed)
    for train in (s for s in SUITES.values() if s.purpose == "training"):
        for bench in (s for s in SUITES.values() if s.purpose == "benchmark"):
            if train.world_seed == bench.world_seed and train.profile == bench.profile:
                q = {s.traversal_seed for s in bench.sequences if s.role == "query"}
                assert not q & {s.traversal_seed for s in train.sequences}, (train.name, bench.name)
    with pytest.raises(ConfigError, match="unknown suite"):
        build_suite("nope")


def test_lookalike_splits_drive_the_confidence_sessions_on_the_same_roads_in_another_world():
    """A training split's look-alike suite: its confidence sessions (same routes, seeds, conditions) in a world of
    another seed on the same road network, so the map's roads are lined by other surroundings."""
    from reradar_core.sim.suites import LOOKALIKE_WORLD_SEED_OFFSET, _shared_world

    for name in ("train-target-boreas", "train-target-loop", "train-target-loop-open", "train-target-offroad"):
        split, look = SUITES[name], SUITES[f"{name}-lookalike"]
        assert look.purpose == "confidence"
        assert look.sequences == tuple(s for s in split.sequences if s.role == "confidence")
        assert look.world_seed == split.world_seed + LOOKALIKE_WORLD_SEED_OFFSET
        assert (look.road_routes, look.profile, look.profile_overrides, look.preset, look.layout, look.radius_m) == \
            (split.road_routes, split.profile, split.profile_overrides, split.preset, split.layout, split.radius_m)
        # no benchmark or training suite lives in a look-alike world
        assert all(s.world_seed != look.world_seed for s in SUITES.values() if s.purpose != "confidence")
    # one tile on the loop's road: the same road network, other surroundings
    a, b = _shared_world("train-target-loop", None), _shared_world("train-target-loop-lookalike", None)
    assert np.array_equal(a.road.points, b.road.points) and a.seed != b.seed
    x, y = a.road.points[0]
    ta, tb = a.tile(int(x // a.tile_m), int(y // a.tile_m)), b.tile(int(x // b.tile_m), int(y // b.tile_m))
    assert len(ta.pts) > 0 and len(tb.pts) > 0
    assert not (ta.pts.shape == tb.pts.shape and np.allclose(ta.pts, tb.pts))


def test_periodic_worlds_repeat_one_tile_layout_on_the_domains_roads():
    """A training split's periodic suite: the benchmark suite's map drive and the split's confidence sessions in a
    world of another seed whose every 40 m tile holds the same layout, so a tile's free-standing objects recur one
    tile further (relative to the tile), on the domain's road network."""
    from reradar_core.sim.suites import PERIODIC_WORLD_SEED_OFFSET, _shared_world
    from reradar_core.training.suites import TRAINING_SPLITS

    for name in ("train-target-boreas", "train-target-loop", "train-target-loop-open", "train-target-offroad"):
        split, per, bench = SUITES[name], SUITES[f"{name}-periodic"], SUITES[str(TRAINING_SPLITS[name])]
        assert per.purpose == "confidence" and per.radius_m == bench.radius_m
        assert per.sequences == (tuple(s for s in bench.sequences if s.role == "database")
                                 + tuple(s for s in split.sequences if s.role == "confidence"))
        assert per.world_seed == split.world_seed + PERIODIC_WORLD_SEED_OFFSET
        assert dict(per.profile_overrides)["tile_types"] == 1
        assert (per.road_routes, per.profile, per.preset, per.layout, per.traffic_per_km, per.car_transmission) == \
            (bench.road_routes, bench.profile, bench.preset, bench.layout, bench.traffic_per_km,
             bench.car_transmission)
        assert all(s.world_seed != per.world_seed for s in SUITES.values() if s.purpose != "confidence")
    assert _shared_world("train-target-loop-periodic", None).profile.tile_types == 1
    # the periodic loop profile on a straight road along x: a tile and the one two tiles further along the road
    # hold the same objects, shifted by two tiles (every tile type-0; the road crosses both at the same offset)
    road = RoadNetwork([np.column_stack([np.linspace(-600.0, 600.0, 601), np.full(601, 13.0)])])
    world = World(road, seed=5, profile=suite_profile(SUITES["train-target-loop-periodic"]))
    shift = 2 * world.tile_m
    for iy in (-1, 0, 1):
        ta, tb = world.tile(1, iy), world.tile(3, iy)
        assert ta.pts.shape == tb.pts.shape and ta.seg.shape == tb.seg.shape and ta.disc.shape == tb.disc.shape
        assert np.allclose(ta.pts + [shift, 0.0], tb.pts) and np.allclose(ta.disc + [shift, 0.0, 0.0], tb.disc)
        assert np.allclose(ta.seg[:, [0, 2]] + shift, tb.seg[:, [0, 2]]) and np.allclose(ta.seg[:, [1, 3]], tb.seg[:, [1, 3]])
    assert len(world.tile(1, 0).pts) > 0
    # the split's own world (every tile its own layout) does not repeat
    own = World(road, seed=5, profile=suite_profile(SUITES["train-target-loop"]))
    assert not (own.tile(1, 0).pts.shape == own.tile(3, 0).pts.shape
                and np.allclose(own.tile(1, 0).pts + [shift, 0.0], own.tile(3, 0).pts))


def test_reversed_routes_revisit_the_same_road_heading_the_other_way():
    """The Two Lochs-like off-road pair and the DCC01-like loop drive their route the other way round."""
    from dataclasses import replace

    from reradar_core.sim.suites import _route_trajectory

    for suite, q_name in (("offroad-sim-hard", "day2-reverse"), ("loop-sim-hard", "laps2-3-reverse")):
        sd = SUITES[suite]
        db_def = next(s for s in sd.sequences if s.role == "database")
        q_def = next(s for s in sd.sequences if s.name == q_name)
        assert q_def.route.reverse and not db_def.route.reverse
        db = _route_trajectory(replace(db_def.route, time_fraction=(0.0, 1.0)), None)
        q = _route_trajectory(q_def.route, None)
        d = np.linalg.norm(q.xy[::25, None] - db.xy[None], axis=2)
        j = d.argmin(axis=1)
        assert np.median(d.min(axis=1)) < 5.0  # same road (another lane)
        dyaw = np.abs(np.angle(np.exp(1j * (q.yaw[::25] - db.yaw[j]))))
        assert np.median(dyaw) > np.radians(150)  # heading the other way


def test_boreas_suite_needs_trajectories_with_clear_error(tmp_path):
    with pytest.raises(DatasetError, match="real Boreas trajectory not found"):
        build_suite("boreas-sim", root=tmp_path, progress=False, trajectory_dir=tmp_path / "none")


def test_cli_sim_suite_help_names_every_suite():
    from reradar_cli import app

    res = CliRunner().invoke(app, ["sim-suite", "--help"], terminal_width=400)
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())
    assert all(name in text for name in SUITES), [n for n in SUITES if n not in text]


def test_cli_sim_renders_a_trajectory(tmp_path):
    from reradar_cli import app

    t = 1_600_000_000_000_000 + np.arange(0, 3_000_001, 250_000)
    s = (t - t[0]) / 1e6
    traj = write_txyyaw_csv(PoseSequence(t, np.column_stack([8.0 * s, 0 * s]), 0 * s), tmp_path / "traj.csv")
    out = tmp_path / "seq"
    res = CliRunner().invoke(app, ["sim", "--trajectory", str(traj), "--out", str(out), "--preset", "mulran",
                                   "--condition", "rain", "--seed", "3", "--every", "2", "--limit", "3"])
    assert res.exit_code == 0, res.output
    seq = load_sequence(out)
    assert seq.layout == "mulran" and len(seq) == 3
    np.testing.assert_allclose(seq.poses.xy[:, 0], [0.0, 4.0, 8.0], atol=1e-6)
    bad = CliRunner().invoke(app, ["sim", "--trajectory", str(traj), "--out", str(out), "--condition", "fog"])
    assert bad.exit_code == 2 and "condition" in bad.output


def test_renders_of_another_simulator_version_are_redone(smoke, monkeypatch):
    from reradar_core.sim import writer

    db = load_sequence(smoke.database[0])
    first = db.scan_paths[0]
    mtime = first.stat().st_mtime_ns
    monkeypatch.setattr(writer, "SIM_VERSION", "other-version")
    assert not writer.is_complete(smoke.database[0])
    build_suite("smoke", root=smoke.root, progress=False)
    assert writer.is_complete(smoke.database[0])
    assert first.stat().st_mtime_ns != mtime


def test_scan_times_follow_radar_pose_files_or_tile_dense_trajectories():
    from reradar_core.sim.trajectories import scan_times

    t4 = 1_600_000_000_000_000 + np.arange(0, 5_000_001, 250_000)  # one pose per sweep (Boreas radar poses)
    p4 = PoseSequence(t4, np.zeros((len(t4), 2)), np.zeros(len(t4)))
    np.testing.assert_array_equal(scan_times(p4), t4[:-1])
    t20 = 1_600_000_000_000_000 + np.arange(0, 5_000_001, 50_000)  # 20 Hz poses: sweeps tile the span
    p20 = PoseSequence(t20, np.zeros((len(t20), 2)), np.zeros(len(t20)))
    st = scan_times(p20, every=2, limit=5)
    np.testing.assert_array_equal(np.diff(st), 500_000)
    assert len(st) == 5
    with pytest.raises(ConfigError):
        scan_times(p20, every=0)


def test_cli_sim_trajectory_with_time_from_zero_needs_a_unit_and_then_renders_true_poses(tmp_path):
    """Regression: a t,x,y,yaw CSV whose t starts at 0 s used to put every scan at the origin silently."""
    from reradar_cli import app

    t_s = np.arange(0.0, 3.01, 0.25)  # 4 Hz poses, relative seconds from 0
    rows = "\n".join(f"{t:.2f},{8.0 * t:.3f},{-2.0 * t:.3f},0.1" for t in t_s)
    traj = tmp_path / "traj.csv"
    traj.write_text("t,x,y,yaw\n" + rows + "\n")
    out = tmp_path / "seq"
    base = ["sim", "--trajectory", str(traj), "--out", str(out), "--preset", "boreas", "--seed", "3", "--limit", "4"]
    refused = CliRunner().invoke(app, base)
    assert refused.exit_code == 2
    assert "--time-unit" in refused.output and "ambiguous" in refused.output
    assert not (out / "radar").exists()  # nothing rendered on a refused input
    res = CliRunner().invoke(app, base + ["--time-unit", "s"])
    assert res.exit_code == 0, res.output
    seq = load_sequence(out)
    assert len(seq) == 4
    np.testing.assert_array_equal(seq.timestamps_us, [0, 250_000, 500_000, 750_000])
    # each scan at the trajectory's pose at its start time: 8 m/s east, 2 m/s south (not all at the origin)
    np.testing.assert_allclose(seq.poses.xy, [[0.0, 0.0], [2.0, -0.5], [4.0, -1.0], [6.0, -1.5]], atol=1e-6)
    np.testing.assert_allclose(seq.poses.yaw, 0.1, atol=1e-12)
    # the same drive in milliseconds with a unit-declaring header renders the same poses
    traj_ms = tmp_path / "traj_ms.csv"
    traj_ms.write_text("t_ms,x,y,yaw\n" + "\n".join(f"{1000 * t:.0f},{8.0 * t:.3f},{-2.0 * t:.3f},0.1"
                                                       for t in t_s) + "\n")
    out_ms = tmp_path / "seq_ms"
    res = CliRunner().invoke(app, ["sim", "--trajectory", str(traj_ms), "--out", str(out_ms), "--limit", "4"])
    assert res.exit_code == 0, res.output
    np.testing.assert_allclose(load_sequence(out_ms).poses.xy, seq.poses.xy, atol=1e-6)
    bad_unit = CliRunner().invoke(app, base + ["--time-unit", "minutes"])
    assert bad_unit.exit_code == 2 and "--time-unit" in bad_unit.output


def test_road_files_are_read_on_their_own_terms(tmp_path):
    """--time-unit is for the trajectory; a road file with absolute times keeps its own unit."""
    from reradar_core.errors import PoseFileError
    from reradar_core.io.poses import write_boreas_radar_poses
    from reradar_core.sim.trajectories import load_road_xy

    t = 1_630_597_331_060_160 + np.arange(3) * 250_000  # absolute µs: would overflow if read as seconds
    absolute = write_boreas_radar_poses(PoseSequence(t, [[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]], np.zeros(3)),
                                        tmp_path / "radar_poses.csv")
    np.testing.assert_allclose(load_road_xy(absolute, "s")[:, 0], [0.0, 1.0, 2.0])
    relative = tmp_path / "rel.csv"
    relative.write_text("t,x,y,yaw\n0.5,5,0,0\n0,4,0,0\n")
    np.testing.assert_allclose(load_road_xy(relative, "s")[:, 0], [4.0, 5.0])  # in time order
    with pytest.raises(PoseFileError, match="ambiguous"):
        load_road_xy(relative)


def test_carry_over_takes_a_render_to_the_current_version_and_leaves_the_old_one(tmp_path, monkeypatch):
    """A byte-identical earlier render becomes this version's by hard links; the old folder keeps its own marker,
    render-version file and metadata (known answer: marker ``<version> <count>``)."""
    import json

    from reradar_core.sim import writer

    monkeypatch.setattr(writer, "SIM_VERSION", "new")
    src, dst = tmp_path / "vold" / "seq", tmp_path / "vnew" / "seq"
    (src / "radar").mkdir(parents=True)
    (src / "radar" / "1.png").write_bytes(b"scan")
    (src / "reradar_sim.json").write_text(json.dumps({"sim_version": "old", "world_seed": 3}))
    (src / writer._STARTED).write_text("old\n")
    assert not writer.carry_over(src, dst, "old")  # not complete yet: nothing to take over
    assert not dst.exists()
    (src / writer.COMPLETE_MARKER).write_text("old 1\n")
    dst.parent.mkdir()
    assert writer.carry_over(src, dst, "old")
    assert writer.is_complete(dst) and (dst / writer.COMPLETE_MARKER).read_text() == "new 1\n"
    assert (dst / writer._STARTED).read_text() == "new\n"
    meta = json.loads((dst / "reradar_sim.json").read_text())
    assert meta["sim_version"] == "new" and meta["world_seed"] == 3 and "old" in meta["carried_over_from"]
    assert (dst / "radar" / "1.png").stat().st_ino == (src / "radar" / "1.png").stat().st_ino  # a hard link
    # the old render is untouched
    assert (src / writer.COMPLETE_MARKER).read_text() == "old 1\n" and (src / writer._STARTED).read_text() == "old\n"
    assert json.loads((src / "reradar_sim.json").read_text())["sim_version"] == "old"
    assert not writer.carry_over(src, dst, "old")  # already complete in this version
    assert not writer.carry_over(src, tmp_path / "other", "older")  # src is not a render of that version


@pytest.mark.parametrize("suite_name", ["smoke", "loop-sim", "offroad-sim"])  # boreas, mulran, oxford layouts
def test_subsampled_render_keeps_the_drive_for_mid_sweep_ground_truth(suite_name, tmp_path):
    """v10: a render of every n-th scan writes the drive's poses between its scans too, so the mid-sweep pose
    ground truth (and a map's keyframe poses) is the drive's own pose at the mean azimuth time, in every layout;
    each scan's own pose is the drive's at its start time."""
    from reradar_core.io.presets import mid_sweep_times_us
    from reradar_core.sim.suites import _route_trajectory

    data = build_suite(suite_name, root=tmp_path / suite_name, progress=False, limit=3)
    sdef = next(d for d in SUITES[suite_name].sequences if d.role == "query")
    seq = data.query_sequences()[0]
    assert SUITES[suite_name].sequences[0].every > 1 or sdef.every > 1  # subsampled: rows between scans matter
    drive = _route_trajectory(sdef.route, None)
    np.testing.assert_allclose(seq.poses.poses, drive.interpolate(seq.timestamps_us), atol=1e-6)
    assert len(seq.track) > 3 * len(seq)  # the drive between the scans, not one row per scan
    truth = drive.interpolate(mid_sweep_times_us(seq.timestamps_us, seq.preset))
    mid = seq.mid_sweep_poses()
    np.testing.assert_allclose(mid[:, :2], truth[:, :2], atol=1e-6)
    np.testing.assert_allclose(np.angle(np.exp(1j * (mid[:, 2] - truth[:, 2]))), 0.0, atol=1e-9)
