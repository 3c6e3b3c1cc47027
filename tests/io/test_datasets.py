"""Sequence reader/writers in the Boreas, Oxford and MulRan layouts (tiny scans made by the tests)."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.errors import DatasetError, PoseFileError
from reradar_core.geometry.se2 import compose, inverse
from reradar_core.io.datasets import (
    detect_layout,
    load_sequence,
    read_oxford_odometry,
    scan_path,
    write_sequence_meta,
    write_sequence_poses,
    write_sequence_scan,
)
from reradar_core.io.poses import PoseSequence, write_boreas_radar_poses, write_mulran_global_pose
from reradar_core.io.scan import RadarScan

T0 = 1_600_000_000_000_000


def _scan(t0_us: int, value: float) -> RadarScan:
    power = np.full((400, 32), value, dtype=np.float32)
    return RadarScan.from_power(power, "boreas", start_time_us=t0_us)


def _write_scans(root, layout: str, times: list[int]) -> None:
    for k, t in enumerate(times):
        write_sequence_scan(root, layout, _scan(t, (k + 1) / 255.0))


def _track(times_us: np.ndarray) -> PoseSequence:
    t = np.asarray(times_us, dtype=np.int64)
    s = (t - t[0]) / 1e6
    return PoseSequence(t, np.column_stack([10.0 * s, 2.0 * s]), 0.1 * s)


def test_boreas_layout_interpolates_poses_at_scan_times(tmp_path):
    root = tmp_path / "seq"
    scan_times = [T0 + 100_000, T0 + 350_000, T0 + 600_000]
    _write_scans(root, "boreas", scan_times)
    # poses at 10 Hz, not at the scan times: the reader must interpolate
    write_boreas_radar_poses(_track(T0 + np.arange(0, 1_000_001, 100_000)), root / "applanix" / "radar_poses.csv")
    seq = load_sequence(root, preset="boreas")
    assert seq.layout == "boreas" and seq.preset.name == "boreas" and len(seq) == 3
    assert seq.timestamps_us.tolist() == scan_times
    expect_x = 10.0 * (np.asarray(scan_times) - T0) / 1e6
    np.testing.assert_allclose(seq.poses.xy[:, 0], expect_x, atol=1e-6)
    np.testing.assert_allclose(seq.poses.yaw, 0.1 * (np.asarray(scan_times) - T0) / 1e6, atol=1e-9)
    scan = seq.load_scan(1)
    assert scan.timestamp_us == scan_times[1]
    assert scan.power[0, 0] == pytest.approx(2 / 255.0)


def test_mulran_layout_nanosecond_names(tmp_path):
    root = tmp_path / "mul"
    times = [T0, T0 + 250_000]
    _write_scans(root, "mulran", times)
    assert scan_path(root, "mulran", T0).name == f"{T0 * 1000}.png"
    write_mulran_global_pose(_track(np.asarray([T0 - 50_000, T0 + 500_000])), root / "global_pose.csv")
    seq = load_sequence(root, preset="boreas")
    assert seq.layout == "mulran"
    assert seq.timestamps_us.tolist() == times
    np.testing.assert_allclose(seq.poses.xy[:, 0], [0.5, 3.0], atol=1e-6)


def test_oxford_layout_integrates_odometry_and_uses_sim_origin(tmp_path):
    root = tmp_path / "ox"
    times = [T0, T0 + 250_000, T0 + 500_000, T0 + 750_000]
    _write_scans(root, "oxford", times)
    world = np.array([[5.0, 1.0, 0.3], [7.0, 2.0, 0.5], [8.0, 4.0, 1.2], [8.5, 7.0, 1.6]])
    gt = PoseSequence(np.asarray(times), world[:, :2], world[:, 2])
    write_sequence_poses(root, "oxford", gt)
    seq = load_sequence(root, preset="oxford")
    assert seq.layout == "oxford"
    # real Oxford data: poses relative to the first scan of the chain
    rel = compose(inverse(world[0])[None], world)
    np.testing.assert_allclose(seq.poses.poses, rel, atol=1e-9)
    # simulated data records the world origin so traversals share one map frame
    write_sequence_meta(root, {"preset": "oxford", "oxford_T_world_origin": world[0].tolist()})
    seq = load_sequence(root)
    np.testing.assert_allclose(seq.poses.poses, world, atol=1e-9)
    assert seq.preset.name == "oxford"


def test_oxford_odometry_frame_convention(tmp_path):
    """Oxford rows are T_dst_src with y to the right and yaw clockwise: converted to y left, yaw CCW."""
    f = tmp_path / "radar_odometry.csv"
    f.write_text(
        "source_timestamp,destination_timestamp,x,y,z,roll,pitch,yaw,source_radar_timestamp,"
        "destination_radar_timestamp\n"
        "2,1,1.0,0.5,0,0,0,0.1,20,10\n"
    )
    track = read_oxford_odometry(f)
    assert track.timestamps_us.tolist() == [10, 20]
    np.testing.assert_allclose(track.poses[0], [0, 0, 0])
    np.testing.assert_allclose(track.poses[1], [1.0, -0.5, -0.1])


def test_detect_layout_and_errors(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        load_sequence(tmp_path / "missing")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DatasetError, match="not a radar sequence"):
        detect_layout(empty)
    no_poses = tmp_path / "nop"
    _write_scans(no_poses, "boreas", [T0])
    with pytest.raises(DatasetError, match="no poses"):
        load_sequence(no_poses)
    with pytest.raises(DatasetError, match="unknown dataset layout"):
        load_sequence(no_poses, layout="kitti")
    # scans outside the pose file's time span are refused, not extrapolated
    write_boreas_radar_poses(_track(np.asarray([T0 + 10_000_000, T0 + 11_000_000])),
                             no_poses / "applanix" / "radar_poses.csv")
    with pytest.raises(DatasetError, match="outside the pose file"):
        load_sequence(no_poses, preset="boreas")


def test_a_scan_in_a_long_gap_between_poses_is_refused(tmp_path):
    """QA session 40: a 10 s gap in the poses (a GNSS outage) was bridged by a straight line without a word; a scan
    inside a gap of more than POSE_GAP_MAX_US is refused, one at a pose row or in a short gap is not."""
    from reradar_core.io.datasets import POSE_GAP_MAX_US, check_pose_span

    root = tmp_path / "gap"
    scans = [T0, T0 + 5_000_000, T0 + 12_000_000]
    _write_scans(root, "boreas", scans)
    write_boreas_radar_poses(_track(np.asarray([T0, T0 + 1_000_000, T0 + 11_000_000, T0 + 12_000_000])),
                             root / "applanix" / "radar_poses.csv")
    with pytest.raises(DatasetError, match=r"falls in a 10 s gap between two poses.*1 scan\(s\) in such gaps"):
        load_sequence(root, preset="boreas")
    track = _track(np.asarray([T0, T0 + 1_000_000, T0 + 11_000_000, T0 + 12_000_000]))
    names = ["a", "b", "c"]
    check_pose_span(track, np.asarray([T0, T0 + 500_000, T0 + 11_000_000]), names)  # rows and a short gap
    short = _track(np.asarray([T0, T0 + POSE_GAP_MAX_US, T0 + 2 * POSE_GAP_MAX_US]))
    check_pose_span(short, np.asarray([T0 + 1_000, T0 + POSE_GAP_MAX_US + 1_000]), names[:2])  # 1 Hz-like rows


def test_broken_oxford_chain_is_reported(tmp_path):
    f = tmp_path / "radar_odometry.csv"
    f.write_text(
        "source_timestamp,destination_timestamp,x,y,z,roll,pitch,yaw,source_radar_timestamp,"
        "destination_radar_timestamp\n"
        "2,1,1.0,0,0,0,0,0,20,10\n"
        "4,3,1.0,0,0,0,0,0,40,30\n"
    )
    with pytest.raises(PoseFileError, match="broken"):
        read_oxford_odometry(f)


def test_subset_every_kth(tmp_path):
    root = tmp_path / "seq"
    times = [T0 + k * 250_000 for k in range(6)]
    _write_scans(root, "boreas", times)
    write_boreas_radar_poses(_track(np.asarray(times)), root / "applanix" / "radar_poses.csv")
    seq = load_sequence(root, preset="boreas").subset(slice(None, None, 2))
    assert len(seq) == 3 and seq.timestamps_us.tolist() == times[::2]
    assert seq.scan_paths[1].stem == str(times[2])
    full = load_sequence(root, preset="boreas")
    masked = full.subset(full.timestamps_us >= times[4])
    assert masked.timestamps_us.tolist() == times[4:] and len(masked.poses) == 2


def test_boreas_folder_with_relative_gpstime_is_refused_unless_simulated(tmp_path):
    """Relative GPSTime (from 0) has no unit a reader could tell; only our simulator's folders (µs by
    construction, marked by reradar_sim.json) are read without one."""
    times = [0, 250_000, 500_000]
    real = tmp_path / "real"
    _write_scans(real, "boreas", times)
    write_boreas_radar_poses(_track(np.asarray(times)), real / "applanix" / "radar_poses.csv")
    with pytest.raises(PoseFileError, match="ambiguous"):
        load_sequence(real, preset="boreas")
    sim = tmp_path / "sim"
    _write_scans(sim, "boreas", times)
    write_boreas_radar_poses(_track(np.asarray(times)), sim / "applanix" / "radar_poses.csv")
    write_sequence_meta(sim, {"preset": "boreas", "sim_version": "2"})
    seq = load_sequence(sim)
    np.testing.assert_allclose(seq.poses.xy[:, 0], [0.0, 2.5, 5.0], atol=1e-9)  # 10 m/s, not all at the origin


def test_mid_sweep_poses_interpolate_the_pose_file_also_after_subset(tmp_path):
    from reradar_core.io.presets import get_preset, mid_sweep_times_us

    # 400 azimuths over 0.25 s: the mean azimuth time is 399 / 2 * 625 us = 124687.5 us after the first
    assert int(mid_sweep_times_us(T0, get_preset("boreas"))) == T0 + 124_688
    times = [T0 + k * 250_000 for k in range(9)]
    _write_scans(tmp_path, "boreas", times)
    pose_times = np.arange(T0 - 100_000, T0 + 2_500_000, 50_000)
    write_boreas_radar_poses(_track(pose_times), tmp_path / "applanix" / "radar_poses.csv")
    write_sequence_meta(tmp_path, {"preset": "boreas", "layout": "boreas"})
    seq = load_sequence(tmp_path)
    mid = seq.mid_sweep_poses()
    # the track moves 10 m/s along x, 2 m/s along y from T0 - 0.1 s: mid-sweep is 0.1247 s after each scan time
    s = (np.asarray(times) - (T0 - 100_000) + 124_688) / 1e6
    np.testing.assert_allclose(mid[:, 0], 10.0 * s, atol=1e-6)
    np.testing.assert_allclose(mid[:, 1], 2.0 * s, atol=1e-6)
    np.testing.assert_allclose(mid[:, 0] - seq.poses.poses[:, 0], 1.24688, atol=1e-6)
    # every 4th scan kept: still interpolated in the file's trajectory, not between the kept scans
    sub = seq.subset(slice(None, None, 4))
    np.testing.assert_allclose(sub.mid_sweep_poses(), mid[::4], atol=1e-9)


def test_explicit_preset_contradicting_the_recorded_one_is_refused(tmp_path):
    """L1: a render recorded as Boreas (0.0596 m/bin) read as Oxford (0.0432 m/bin) would put every return 28 %
    too close: refused with the recorded preset named; the recorded preset itself is accepted."""
    root = tmp_path / "seq"
    times = [T0, T0 + 250_000]
    _write_scans(root, "boreas", times)
    write_sequence_poses(root, "boreas", _track(np.array(times)))
    write_sequence_meta(root, {"preset": "boreas", "sim_version": "10"})
    with pytest.raises(DatasetError, match=r"rendered with radar preset 'boreas'.*not 'oxford'.*-27\.5 %.*read at 72\.71 m"):
        load_sequence(root, preset="oxford")
    assert load_sequence(root, preset="boreas").preset.name == "boreas"
    assert load_sequence(root).preset.name == "boreas"


def test_binary_pose_file_is_a_pose_file_error(tmp_path):
    from reradar_core.io.poses import read_poses

    path = tmp_path / "grey.png"
    path.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(PoseFileError, match="not a text pose file"):
        read_poses(path, "s")


def test_a_boreas_folder_must_name_its_radar_preset(tmp_path):
    """QA (session 24): a real Boreas folder read without a preset got the layout's default, boreas (0.0596 m/bin);
    a 2021 recording (boreas-2021, 0.04381 m/bin, the same 3,360 bins) had every range 1.36x too long and was answered
    1.5 m off at confidence 1. Without simulator metadata a Boreas folder must name its preset; Oxford and MulRan,
    one range geometry each, need none."""
    times = [1_600_000_000_000_000, 1_600_000_000_250_000, 1_600_000_000_500_000]
    real = tmp_path / "real"
    _write_scans(real, "boreas", times)
    write_boreas_radar_poses(_track(np.asarray(times)), real / "applanix" / "radar_poses.csv")
    with pytest.raises(DatasetError, match=r"boreas 0.0596 m/bin, boreas-2021 0.04381 m/bin.*--preset"):
        load_sequence(real)
    assert load_sequence(real, preset="boreas-2021").preset.range_resolution_m == pytest.approx(0.04381)
    write_sequence_meta(real, {"preset": "boreas-2021"})  # a render names its own
    assert load_sequence(real).preset.name == "boreas-2021"


def test_a_short_clip_read_in_a_unit_1000x_too_coarse_is_refused(tmp_path):
    """QA (session 24): the unit check skipped pose files of 50 m of path or less, so a 19-scan, 47.5 m clip of relative
    µs read with --time-unit ms placed every scan on its first pose (RingKey Recall@1 100 %, ReRadar 10 m off)."""
    times = [k * 250_000 for k in range(19)]
    root = tmp_path / "clip"
    _write_scans(root, "boreas", times)
    write_boreas_radar_poses(_track(np.asarray(times)), root / "applanix" / "radar_poses.csv")  # 10.2 m/s, 46 m
    for unit in ("ms", "s"):
        with pytest.raises(DatasetError, match=r"every scan would be placed on 0\.0 m .*pass --time-unit us"):
            load_sequence(root, preset="boreas", pose_time_unit=unit)
    assert load_sequence(root, preset="boreas", pose_time_unit="us").poses.path_length_m() > 40.0


def test_a_rendered_mulran_folder_is_read_in_ns_whatever_its_start(tmp_path):
    """QA (session 24): a MulRan render whose times start at 1,000 s (1e12 ns) was refused as 'absolute times in ms'
    and advised --time-unit ms (wrong); a render's MulRan times are ns by the format, as real ones."""
    times = [1_000_000_000 + k * 250_000 for k in range(8)]  # µs: 1,000 s on
    root = tmp_path / "m"
    _write_scans(root, "mulran", times)
    write_mulran_global_pose(_track(np.asarray(times)), root / "global_pose.csv")
    with pytest.raises(PoseFileError, match="absolute times in ms"):  # without the render's marker: not guessed
        load_sequence(root)
    write_sequence_meta(root, {"preset": "mulran", "sim_version": "10"})
    seq = load_sequence(root)
    np.testing.assert_allclose(seq.poses.xy[:, 0], 10.0 * np.arange(8) * 0.25, atol=1e-6)


def test_scans_just_past_the_pose_file_continue_its_motion(tmp_path):
    """QA (session 24): scans up to 0.5 s past the last pose row are accepted, and were given the last pose held: a
    pose file ending at the last scan's timestamp held that scan's mid-sweep pose (125 ms on) 1.3 m back at 10 m/s,
    and two rows short put the last scan 2.5 m back. Within the slack the end step's motion now continues."""
    times = [T0 + k * 250_000 for k in range(8)]
    track = _track(np.asarray(times))  # 10 m/s along x, 2 m/s along y, yaw 0.1 rad/s
    root = tmp_path / "seq"
    _write_scans(root, "boreas", times)
    write_boreas_radar_poses(track.subset(np.arange(6)), root / "applanix" / "radar_poses.csv")  # 2 rows short
    seq = load_sequence(root, preset="boreas")
    t = np.asarray(times, np.float64)
    np.testing.assert_allclose(seq.poses.xy[:, 0], 10.0 * (t - T0) / 1e6, atol=1e-6)
    mid = seq.mid_sweep_poses()
    from reradar_core.io.presets import mid_sweep_times_us

    tm = (mid_sweep_times_us(np.asarray(times), seq.preset) - T0) / 1e6
    np.testing.assert_allclose(mid[:, 0], 10.0 * tm, atol=1e-6)
    np.testing.assert_allclose(mid[:, 2], 0.1 * tm, atol=1e-9)
    held = track.subset(np.arange(6)).interpolate(np.asarray(times[-1:]))  # the default still clamps
    assert held[0, 0] == pytest.approx(track.xy[5, 0])


def test_a_boreas_heading_column_in_degrees_is_refused(tmp_path):
    """QA re-test (session 24): a Boreas radar_poses.csv whose heading held degrees (4.0 on a road at 4 degrees) was
    read as 4 rad and built a map 135 degrees off; the format's heading is radians, and the plain-yaw guard now
    covers it."""
    times = [T0 + k * 250_000 for k in range(20)]
    t = (np.asarray(times, np.float64) - T0) / 1e6
    c, s = np.cos(np.radians(4.0)), np.sin(np.radians(4.0))
    xy = np.column_stack([10.0 * t * c, 10.0 * t * s])
    root = tmp_path / "deg"
    _write_scans(root, "boreas", times)
    write_boreas_radar_poses(PoseSequence(np.asarray(times), xy, np.full(20, 4.0)), root / "applanix" / "radar_poses.csv")
    with pytest.raises(PoseFileError, match="heading column is read as radians.*holds its heading in radians"):
        load_sequence(root, preset="boreas")
    write_boreas_radar_poses(PoseSequence(np.asarray(times), xy, np.full(20, np.radians(4.0))),
                             root / "applanix" / "radar_poses.csv")
    assert load_sequence(root, preset="boreas").poses.yaw[0] == pytest.approx(np.radians(4.0))


def test_a_relative_clock_that_also_reads_as_an_absolute_time_is_read_in_the_unit_given(tmp_path):
    """QA re-test (session 24): a Boreas render starting at 1,000 s (GPSTime 1e9 µs, which also reads as absolute s in
    2001) could be loaded in no unit: none -> 'absolute s', s -> 'probably us', us -> 'absolute s' again. A declared
    unit is now refused only when its reading is no plausible relative clock (more than a year)."""
    times = [1_000_000_000 + k * 250_000 for k in range(12)]
    root = tmp_path / "r"
    _write_scans(root, "boreas", times)
    write_boreas_radar_poses(_track(np.asarray(times)), root / "applanix" / "radar_poses.csv")
    assert len(load_sequence(root, preset="boreas", pose_time_unit="us")) == 12
    write_sequence_meta(root, {"preset": "boreas", "sim_version": "10"})
    assert load_sequence(root).poses.xy[-1, 0] == pytest.approx(27.5)
    from reradar_core.io.poses import gps_time_to_us

    with pytest.raises(PoseFileError, match="absolute UTC times in ns, not us"):  # 1.6e18 read as us: 50,000 years
        gps_time_to_us(np.array([1_600_000_000_000_000_000, 1_600_000_000_250_000_000]), "us")


def test_mulran_times_that_read_as_absolute_ms_name_both_readings(tmp_path):
    """QA re-test (session 24): 1e12 in a plain MulRan file was called absolute ms, and --time-unit ms advised; it may
    as well be a relative ns clock from 1,000 s, the format's unit."""
    times = [1_000_000_000 + k * 250_000 for k in range(8)]
    root = tmp_path / "m"
    _write_scans(root, "mulran", times)
    write_mulran_global_pose(_track(np.asarray(times)), root / "global_pose.csv")
    with pytest.raises(PoseFileError, match=r"--time-unit ms if they are, --time-unit ns if they are a relative clock"):
        load_sequence(root)
    assert len(load_sequence(root, pose_time_unit="ns")) == 8


def test_a_pose_file_faster_than_any_vehicle_is_refused():
    """Positions in millimetres (or times in a unit too fine) make a drive of thousands of m/s: refused by name
    (QA session 36: build-map stored keyframes 1000x apart and bench found no revisit, without a word)."""
    from reradar_core.io.datasets import check_pose_speed

    t = np.arange(80, dtype=np.int64) * 250_000
    xy = np.stack([np.arange(80) * 2.0, np.zeros(80)], axis=1)  # 8 m/s
    check_pose_speed(PoseSequence(t, xy, np.zeros(80)))
    check_pose_speed(PoseSequence(t, xy * 0.001, np.zeros(80)))  # under 20 m of path: a vehicle standing, not judged
    with pytest.raises(DatasetError, match=r"mean speed of 8e\+03 m/s .*millimetres.*\(--time-unit\)"):
        check_pose_speed(PoseSequence(t, xy * 1000, np.zeros(80)), "poses.csv")
    with pytest.raises(DatasetError, match=r"read in \(name the column t_s\)$"):  # the service's own advice
        check_pose_speed(PoseSequence(t, xy * 1000, np.zeros(80)), "poses.csv", how="name the column t_s")


_OXFORD_HEADER = ("source_timestamp,destination_timestamp,x,y,z,roll,pitch,yaw,source_radar_timestamp,"
                  "destination_radar_timestamp\n")


def test_oxford_odometry_in_degrees_or_with_nan_is_refused_by_line(tmp_path):
    """QA session 38: the Oxford reader had none of the Boreas reader's unit checks: yaw in degrees built a map whose
    headings turned by radians at every corner, and a NaN was reported as 'row 0' of no file."""
    f = tmp_path / "radar_odometry.csv"
    f.write_text(_OXFORD_HEADER + "2,1,2.0,0,0,0,0,0.5,20,10\n3,2,2.0,0,0,0,0,4.0,30,20\n")
    with pytest.raises(PoseFileError, match=r"radar_odometry.csv:3: yaw -?4 turns more than 90 degrees.*radians"):
        read_oxford_odometry(f)
    f.write_text(_OXFORD_HEADER + "2,1,2.0,0,0,0,0,0.5,20,10\n3,2,nan,0,0,0,0,0.1,30,20\n")
    with pytest.raises(PoseFileError, match=r"radar_odometry.csv:3: NaN or infinite value"):
        read_oxford_odometry(f)


def test_oxford_odometry_in_millimetres_is_refused_by_speed(tmp_path):
    root = tmp_path / "ox"
    times = [T0 + k * 250_000 for k in range(40)]
    _write_scans(root, "oxford", times)
    rows = [f"{t1},{t0},{2500.0},0,0,0,0,0,{t1},{t0}\n" for t0, t1 in zip(times[:-1], times[1:], strict=True)]
    (root / "gt").mkdir()
    (root / "gt" / "radar_odometry.csv").write_text(_OXFORD_HEADER + "".join(rows))  # 2.5 m per frame, in mm
    with pytest.raises(DatasetError, match="faster than sound.*metres"):
        load_sequence(root)


def test_layout_detection_names_a_file_and_two_layouts(tmp_path):
    """QA session 38: --dataset on the pose file said 'does not exist'; a stray MulRan scan folder beside radar/
    made a 1-keyframe MulRan map of a 30-scan Boreas drive."""
    root = tmp_path / "seq"
    times = [T0 + k * 250_000 for k in range(4)]
    _write_scans(root, "boreas", times)
    write_boreas_radar_poses(_track(np.asarray(times)), root / "applanix" / "radar_poses.csv")
    with pytest.raises(DatasetError, match="is a file; give the sequence folder"):
        load_sequence(root / "applanix" / "radar_poses.csv")
    (root / "sensor_data" / "radar" / "polar").mkdir(parents=True)
    with pytest.raises(DatasetError, match="two layouts.*--layout"):
        load_sequence(root, preset="boreas")
    assert len(load_sequence(root, layout="boreas", preset="boreas")) == 4


def test_a_scan_with_an_upper_case_suffix_is_read(tmp_path):
    root = tmp_path / "seq"
    times = [T0 + k * 250_000 for k in range(4)]
    _write_scans(root, "boreas", times)
    write_boreas_radar_poses(_track(np.asarray(times)), root / "applanix" / "radar_poses.csv")
    (root / "radar" / f"{times[1]}.png").rename(root / "radar" / f"{times[1]}.PNG")
    seq = load_sequence(root, preset="boreas")
    assert seq.timestamps_us.tolist() == times and seq.load_scan(1).timestamp_us == times[1]


def test_a_single_pose_glitch_is_named(tmp_path):
    root = tmp_path / "seq"
    times = [T0 + k * 250_000 for k in range(40)]
    _write_scans(root, "boreas", times[::8])
    track = _track(np.asarray(times))
    xy = track.xy.copy()
    xy[21, 0] += 500.0  # one GNSS row 500 m off
    write_boreas_radar_poses(PoseSequence(track.timestamps_us, xy, track.yaw), root / "applanix" / "radar_poses.csv")
    with pytest.raises(DatasetError, match=rf"pose at {times[21]} us lies .* faster than sound.*2 such step"):
        load_sequence(root, preset="boreas")


def test_scans_outside_a_pose_file_on_another_clock_are_told_the_shift():
    """QA session 41: a GPS-time pose file (18 s ahead of UTC) recorded beside the radar leaves the scans outside its
    span, and the span check fired before the build's pose-clock check could say so: the message now does when both
    ends of the two spans are shifted alike."""
    from reradar_core.io.datasets import check_pose_span

    scans = T0 + np.arange(40) * 250_000
    names = [f"{t}.png" for t in scans]
    with pytest.raises(DatasetError, match=r"both ends of the scans' span lie -18\.00 s from the pose file's: a pose "
                                           r"file on another clock \(GPS time runs 18 s ahead of UTC\)\? Add -18\.00 s "
                                           r"to its times$"):
        check_pose_span(_track(scans + 18_000_000), scans, names)
    with pytest.raises(DatasetError, match=r"lie \+1\.00 s from the pose file's: a pose file on another clock\? Add "
                                           r"\+1\.00 s to its times$"):
        check_pose_span(_track(scans - 1_000_000), scans, names)
    with pytest.raises(DatasetError) as short:  # a pose file that merely stops early: no clock advice
        check_pose_span(_track(scans[:20]), scans, names)
    assert "another clock" not in str(short.value)
    check_pose_span(_track(scans - 200_000), scans, names)  # within the slack: accepted
    # a log that runs beyond the scans, on another clock: long enough to cover them, off at one end
    wider = np.concatenate([scans[0] - np.arange(8, 0, -1) * 250_000, scans, scans[-1] + np.arange(1, 9) * 250_000])
    with pytest.raises(DatasetError, match=r"the pose file is long enough to cover the scans but starts 16\.00 s after "
                                           r"them and ends 20\.00 s after them: a pose file on another clock \(GPS "
                                           r"time runs 18 s ahead of UTC\) or of another drive\?$"):
        check_pose_span(_track(wider + 18_000_000), scans, names)
