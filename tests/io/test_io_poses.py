"""Pose file readers/writers: Boreas (ns and µs GPSTime), MulRan, plain t,x,y,yaw; errors name file and line."""

from __future__ import annotations

import numpy as np
import pytest

from reradar_core.errors import PoseFileError
from reradar_core.io.poses import (
    BOREAS_COLUMNS,
    PoseSequence,
    absolute_time_unit,
    read_boreas_radar_poses,
    read_mulran_global_pose,
    read_poses,
    read_txyyaw_csv,
    to_microseconds,
    write_boreas_radar_poses,
    write_mulran_global_pose,
    write_txyyaw_csv,
)

HEADER = ",".join(BOREAS_COLUMNS)
# Same shapes as the two real Boreas files: GPSTime in nanoseconds (2021-08-05) and in microseconds (2021-09-02).
BOREAS_NS = HEADER + """
1628184886551599081,623425.5464750652,4848820.9989206735,154.06,-0.0007,-0.0008,-0.0001,3.1313,0.0197,0.2367720262139094,6.8e-05,-0.0008,-0.0049
1628184886801550666,623425.5464652807,4848820.998891991,154.06,0.0005,-0.0007,-0.0001,3.1312,0.0197,0.23675085346175226,-0.0008,-0.0062,0.0008
1628184887051601000,623427.0,4848822.5,154.06,0.0,0.0,0.0,3.13,0.019,-3.0,0.0,0.0,0.0
"""
BOREAS_US = HEADER + """
1630597331060160,623422.8507264568,4848820.469537824,153.97,-0.0002,0.0002,7.4e-05,3.1262,0.0318,0.25671182385755154,0.0013,-0.0057,0.0011
1630597331310779,623422.8507496119,4848820.469538635,153.97,-0.0007,0.0004,-0.0004,3.1262,0.0319,0.25673404594601285,0.0015,-0.0006,0.0005
"""


def _write(tmp_path, name: str, text: str):
    p = tmp_path / name
    p.write_text(text.lstrip("\n"))
    return p


def test_boreas_nanosecond_gpstime(tmp_path):
    poses = read_boreas_radar_poses(_write(tmp_path, "radar_poses.csv", BOREAS_NS))
    assert len(poses) == 3
    np.testing.assert_array_equal(poses.timestamps_us, [1628184886551599, 1628184886801550, 1628184887051601])
    np.testing.assert_allclose(poses.xy[0], [623425.5464750652, 4848820.9989206735])
    np.testing.assert_allclose(poses.yaw[:2], [0.2367720262139094, 0.23675085346175226])
    assert poses.yaw[2] == pytest.approx(-3.0)


def test_boreas_microsecond_gpstime(tmp_path):
    poses = read_boreas_radar_poses(_write(tmp_path, "radar_poses.csv", BOREAS_US))
    np.testing.assert_array_equal(poses.timestamps_us, [1630597331060160, 1630597331310779])
    np.testing.assert_allclose(poses.xy[1], [623422.8507496119, 4848820.469538635])
    assert poses.yaw[0] == pytest.approx(0.25671182385755154)


def test_read_poses_dispatches_on_first_line(tmp_path):
    assert len(read_poses(_write(tmp_path, "a.csv", BOREAS_US))) == 2
    assert len(read_poses(_write(tmp_path, "b.csv", "t_s,x,y,yaw\n1.5,2,3,0.1\n2.5,3,4,0.2\n"))) == 2
    mulran = "1566535872045000000,1,0,0,10,0,1,0,20,0,0,1,0\n"
    assert read_poses(_write(tmp_path, "c.csv", mulran)).timestamps_us[0] == 1566535872045000
    with pytest.raises(PoseFileError, match="c2.csv:1: unrecognised"):
        read_poses(_write(tmp_path, "c2.csv", "a,b\n1,2\n"))


def _random_poses(n: int = 7, seed: int = 0) -> PoseSequence:
    rng = np.random.default_rng(seed)
    t = 1630597331060160 + np.cumsum(rng.integers(200_000, 300_000, n))
    # a drive round a bend of random radius and start, headings along it (plus one mounting angle): the readers
    # refuse headings that do not follow the travel
    a = rng.uniform(-np.pi, np.pi) + np.cumsum(rng.uniform(0.05, 0.2, n))
    radius = rng.uniform(50.0, 200.0)
    xy = radius * np.c_[np.cos(a), np.sin(a)] + [623000.0, 4848000.0] + rng.uniform(-1e3, 1e3, 2)
    return PoseSequence(t, xy, a + np.pi / 2 + rng.uniform(-np.pi, np.pi))


@pytest.mark.parametrize(
    "writer,reader",
    [
        (write_boreas_radar_poses, read_boreas_radar_poses),
        (write_mulran_global_pose, read_mulran_global_pose),
        (write_txyyaw_csv, read_txyyaw_csv),
    ],
)
def test_writer_reader_round_trip(tmp_path, writer, reader):
    poses = _random_poses()
    back = reader(writer(poses, tmp_path / "poses.csv"))
    np.testing.assert_array_equal(back.timestamps_us, poses.timestamps_us)
    np.testing.assert_allclose(back.xy, poses.xy, atol=1e-6)
    np.testing.assert_allclose(np.cos(back.yaw - poses.yaw), 1.0, atol=1e-12)
    # read_poses recognises every format it writes
    again = read_poses(tmp_path / "poses.csv")
    np.testing.assert_array_equal(again.timestamps_us, poses.timestamps_us)


def test_mulran_rotation_gives_yaw(tmp_path):
    yaw = 2.5
    c, s = np.cos(yaw), np.sin(yaw)
    line = f"1000,{c},{-s},0,5.0,{s},{c},0,-7.0,0,0,1,0.5\n"
    poses = read_mulran_global_pose(_write(tmp_path, "global_pose.csv", line))
    assert poses.yaw[0] == pytest.approx(yaw)
    np.testing.assert_allclose(poses.xy[0], [5.0, -7.0])
    assert poses.timestamps_us[0] == 1  # ns -> µs


def test_malformed_boreas_names_file_and_line(tmp_path):
    bad = BOREAS_US.replace("623422.8507496119", "oops")
    with pytest.raises(PoseFileError, match=r"bad\.csv:3: non-numeric"):
        read_boreas_radar_poses(_write(tmp_path, "bad.csv", bad))
    short = HEADER + "\n1630597331060160,1,2\n"
    with pytest.raises(PoseFileError, match=r"short\.csv:2: expected at least 10 columns \(a Boreas radar_poses\.csv: GPSTime,easting,northing,"):
        read_boreas_radar_poses(_write(tmp_path, "short.csv", short))
    nan = BOREAS_US.replace("0.25673404594601285", "nan")
    with pytest.raises(PoseFileError, match=r"nan\.csv:3: NaN"):
        read_boreas_radar_poses(_write(tmp_path, "nan.csv", nan))


def test_malformed_other_formats(tmp_path):
    with pytest.raises(PoseFileError, match=r"t\.csv:3: non-numeric"):
        read_txyyaw_csv(_write(tmp_path, "t.csv", "t_s,x,y,yaw\n1,2,3,4\n2,x,3,4\n"))
    with pytest.raises(PoseFileError, match=r"m\.csv:2: timestamp 'abc'"):
        read_mulran_global_pose(_write(tmp_path, "m.csv", "1,1,0,0,0,0,1,0,0,0,0,1,0\nabc,1,0,0,0,0,1,0,0,0,0,1,0\n"))
    with pytest.raises(PoseFileError, match="no pose rows"):
        read_txyyaw_csv(_write(tmp_path, "empty.csv", "t,x,y,yaw\n"))
    with pytest.raises(PoseFileError, match="no such pose file"):
        read_poses(tmp_path / "missing.csv")


def test_pose_sequence_interpolation_wraps_yaw():
    seq = PoseSequence([0, 100], [[0.0, 0.0], [10.0, -2.0]], [np.pi - 0.1, -np.pi + 0.1])
    mid = seq.interpolate(50)
    np.testing.assert_allclose(mid[:2], [5.0, -1.0])
    assert abs(abs(mid[2]) - np.pi) < 1e-9  # halfway across the +-pi seam, not through 0
    np.testing.assert_allclose(seq.interpolate(np.array([-10, 500]))[:, 0], [0.0, 10.0])  # clamped


# ------------------------------------------------------------------ time units: never a silent guess
RELATIVE = "t,x,y,yaw\n0,0,0,0\n0.25,2,0,0\n0.5,4,0,0\n"


def test_absolute_time_unit_windows_are_disjoint():
    assert absolute_time_unit(np.array([1_630_597_331.06])) == "s"
    assert absolute_time_unit(np.array([1_630_597_331_060])) == "ms"
    assert absolute_time_unit(np.array([1_630_597_331_060_160])) == "us"
    assert absolute_time_unit(np.array([1_628_184_886_551_599_081])) == "ns"
    # relative times (from 0), or values between two windows, have no unit
    assert absolute_time_unit(np.array([0.0, 0.25])) is None
    assert absolute_time_unit(np.array([250_000, 500_000])) is None
    assert absolute_time_unit(np.array([5e10])) is None
    # a file mixing magnitudes is not absolute in one unit
    assert absolute_time_unit(np.array([1_630_597_331, 1_630_597_331_060_160])) is None


def test_to_microseconds_is_exact_for_nanosecond_integers():
    ns = np.array([1_628_184_886_551_599_081, 1_628_184_886_801_550_666], dtype=np.int64)
    np.testing.assert_array_equal(to_microseconds(ns, "ns"), [1_628_184_886_551_599, 1_628_184_886_801_550])
    np.testing.assert_array_equal(to_microseconds(np.array([0.0, 0.25, 1.5]), "s"), [0, 250_000, 1_500_000])
    np.testing.assert_array_equal(to_microseconds(np.array([0, 250]), "ms"), [0, 250_000])
    with pytest.raises(PoseFileError, match="unknown time unit 'min'"):
        to_microseconds(np.array([1]), "min")
    # Boreas ns stamps taken for seconds would wrap around int64: refused, not wrapped
    with pytest.raises(PoseFileError, match="overflow int64 microseconds; is the time unit 's' right"):
        to_microseconds(ns, "s")


def test_relative_txyyaw_times_are_refused_without_a_unit(tmp_path):
    path = _write(tmp_path, "rel.csv", RELATIVE)
    with pytest.raises(PoseFileError, match=r"rel\.csv: column t: timestamps 0 \.\. 0\.5 .*ambiguous.*--time-unit"):
        read_txyyaw_csv(path)
    with pytest.raises(PoseFileError, match="ambiguous"):
        read_poses(path)
    np.testing.assert_array_equal(read_txyyaw_csv(path, "s").timestamps_us, [0, 250_000, 500_000])
    np.testing.assert_array_equal(read_poses(path, time_unit="ms").timestamps_us, [0, 250, 500])
    # the header may declare the unit; a conflicting explicit unit is an error, not a silent choice
    declared = _write(tmp_path, "declared.csv", RELATIVE.replace("t,x", "t_s,x"))
    np.testing.assert_array_equal(read_txyyaw_csv(declared).timestamps_us, [0, 250_000, 500_000])
    with pytest.raises(PoseFileError, match="names the time column 't_s' .s., but the time unit given is 'ms'.*"
                                            "rename the column t_ms"):
        read_txyyaw_csv(declared, "ms")
    # absolute UTC seconds need no unit
    absolute = _write(tmp_path, "abs.csv", "t,x,y,yaw\n1630597331.06016,0,0,0\n1630597331.31078,1,0,0\n")
    np.testing.assert_array_equal(read_txyyaw_csv(absolute).timestamps_us, [1630597331060160, 1630597331310780])
    # headerless 4-column rows are read as t,x,y,yaw too
    headerless = _write(tmp_path, "nohead.csv", "1630597331060160,0,0,0\n1630597331310779,1,0,0\n")
    np.testing.assert_array_equal(read_poses(headerless).timestamps_us, [1630597331060160, 1630597331310779])


def test_relative_boreas_gpstime_is_refused_without_a_unit(tmp_path):
    rel = HEADER + "\n0,0,0,0,0,0,0,0,0,0.1,0,0,0\n250000,2,0,0,0,0,0,0,0,0.1,0,0,0\n"
    path = _write(tmp_path, "radar_poses.csv", rel)
    with pytest.raises(PoseFileError, match="GPSTime: timestamps 0 .. 250000 are not absolute UTC times"):
        read_boreas_radar_poses(path)
    np.testing.assert_array_equal(read_boreas_radar_poses(path, "us").timestamps_us, [0, 250_000])
    np.testing.assert_array_equal(read_boreas_radar_poses(path, "ns").timestamps_us, [0, 250])


def test_mulran_is_nanoseconds_and_refuses_absolute_times_in_another_unit(tmp_path):
    us_line = "1566535872045000,1,0,0,10,0,1,0,20,0,0,1,0\n"  # absolute time, but in µs
    path = _write(tmp_path, "global_pose.csv", us_line)
    with pytest.raises(PoseFileError, match="MulRan timestamps are nanoseconds.*--time-unit us"):
        read_mulran_global_pose(path)
    assert read_mulran_global_pose(path, "us").timestamps_us[0] == 1566535872045000
    # relative ns from 0 are the format's own unit
    rel = _write(tmp_path, "rel_pose.csv", "0,1,0,0,0,0,1,0,0,0,0,1,0\n250000000,1,0,0,2,0,1,0,0,0,0,1,0\n")
    np.testing.assert_array_equal(read_mulran_global_pose(rel).timestamps_us, [0, 250_000])


def test_txyyaw_yaw_unit_from_the_header(tmp_path):
    rows = "1.0,0,0,90\n2.0,1,0,-180\n"
    deg = read_txyyaw_csv(_write(tmp_path, "deg.csv", "t_s,x,y,yaw_deg\n" + rows))
    np.testing.assert_allclose(deg.yaw, [np.pi / 2, np.pi])  # -180 deg wraps to +pi
    rad = read_poses(_write(tmp_path, "rad.csv", "t_s,x,y,yaw_rad\n1.0,0,0,1.5\n2.0,1,0,-0.5\n"))
    np.testing.assert_allclose(rad.yaw, [1.5, -0.5])
    # explicit radians may exceed 2 pi (an unwrapped heading): accepted and wrapped
    np.testing.assert_allclose(read_poses(_write(tmp_path, "unwrapped.csv", "t_s,x,y,YAW_RAD\n1.0,0,0,7.0\n")).yaw,
                               [7.0 - 2 * np.pi])
    # plain yaw stays radians, as before: 2 pi itself is still radians
    np.testing.assert_allclose(read_poses(_write(tmp_path, "plain.csv", "t_s,x,y,yaw\n1.0,0,0,6.283185\n")).yaw,
                               [6.283185 - 2 * np.pi], atol=1e-9)


def test_plain_yaw_beyond_two_pi_is_refused_as_probable_degrees(tmp_path):
    for name, text, line in (("plain.csv", "t_s,x,y,yaw\n1.0,0,0,0.5\n2.0,1,0,90\n", 3),
                             ("headerless.csv", "1630597331.0,0,0,-45\n1630597332.0,1,0,0\n", 1)):
        with pytest.raises(PoseFileError, match=rf"{name}:{line}: yaw .* beyond 2 pi.*yaw_deg") as err:
            read_poses(_write(tmp_path, name, text))
        assert "radians" in str(err.value)
    with pytest.raises(PoseFileError, match="4th column is named 'heading'; name it yaw_deg"):
        read_txyyaw_csv(_write(tmp_path, "named.csv", "t_s,x,y,heading\n1.0,0,0,0.5\n"))


def test_positions_beyond_the_coordinate_bound_are_refused_in_every_format(tmp_path):
    from reradar_core.io.poses import MAX_ABS_COORDINATE_M

    assert MAX_ABS_COORDINATE_M == 1e7
    with pytest.raises(PoseFileError, match=r"far.csv:3: position .* more than 1e\+07 m"):
        read_poses(_write(tmp_path, "far.csv", "t_s,x,y,yaw\n1.0,0,0,0\n2.0,1e300,0,0\n"))
    with pytest.raises(PoseFileError, match=r"neg.csv:2: position"):
        read_poses(_write(tmp_path, "neg.csv", "t_s,x,y,yaw\n1.0,0,-1.0000001e7,0\n"))
    far = PoseSequence([1_630_597_331_060_160, 1_630_597_331_310_779], [[0.0, 0.0], [0.0, 2e7]], [0.0, 0.0])
    with pytest.raises(PoseFileError, match="position"):
        read_boreas_radar_poses(write_boreas_radar_poses(far, tmp_path / "b.csv"))
    with pytest.raises(PoseFileError, match="position"):
        read_mulran_global_pose(write_mulran_global_pose(far, tmp_path / "m.csv"))
    # a UTM position (northing below 1e7 m) is fine
    utm = PoseSequence([1_630_597_331_060_160], [[623422.85, 9_999_999.0]], [0.1])
    assert read_poses(write_txyyaw_csv(utm, tmp_path / "utm.csv")).xy[0, 1] == 9_999_999.0


def test_an_explicit_unit_that_contradicts_absolute_times_is_refused(tmp_path):
    """QA (session 20): ``--time-unit us`` on the nanosecond Boreas file read it as a 13-day drive at 7 mm/s."""
    path = _write(tmp_path, "radar_poses.csv", BOREAS_NS)
    with pytest.raises(PoseFileError, match="absolute UTC times in ns, not us"):
        read_boreas_radar_poses(path, "us")
    assert len(read_boreas_radar_poses(path, "ns")) == 3  # the right unit, stated, is fine
    rel = _write(tmp_path, "rel.csv", "t,x,y,yaw\n0,0,0,0\n1,1,0,0\n")
    assert read_txyyaw_csv(rel, "s").timestamps_us[-1] == 1_000_000  # relative times take any unit


def test_a_time_given_twice_is_refused(tmp_path):
    """Code audit (session 20): two rows at one time loaded, and interpolation kept one of them silently."""
    path = _write(tmp_path, "dup.csv", "t_s,x,y,yaw\n1,0,0,0\n1,10,0,0\n2,20,0,0\n")
    with pytest.raises(PoseFileError, match="appear twice"):
        read_txyyaw_csv(path)


def _straight(heading_deg: float, yaw_text: str, n: int = 8, header: str = "t_s,x,y,yaw") -> str:
    """A straight drive at ``heading_deg``, 2 m per 0.25 s; each row's yaw column is ``yaw_text``."""
    c, s = np.cos(np.radians(heading_deg)), np.sin(np.radians(heading_deg))
    rows = [f"{0.25 * i},{2 * i * c:.4f},{2 * i * s:.4f},{yaw_text}" for i in range(n)]
    return header + "\n" + "\n".join(rows) + "\n"


def test_plain_yaw_in_degrees_within_two_pi_is_refused(tmp_path):
    """QA 5: a road at 4 degrees with yaw 4.0 in a plain yaw column was read as 4 rad (heading -131 deg)."""
    with pytest.raises(PoseFileError, match=r"deg\.csv: the yaw column is read as radians.*name the column yaw_deg"):
        read_poses(_write(tmp_path, "deg.csv", _straight(4.0, "4.0")))
    # the same numbers declared as degrees, or as radians on purpose, are read as declared
    assert read_poses(_write(tmp_path, "d.csv", _straight(4.0, "4.0", header="t_s,x,y,yaw_deg"))).yaw[0] == \
        pytest.approx(np.radians(4.0))
    assert read_poses(_write(tmp_path, "r.csv", _straight(4.0, "4.0", header="t_s,x,y,yaw_rad"))).yaw[0] == \
        pytest.approx(4.0 - 2 * np.pi)
    # real radians along the road pass, also with a reversing stretch (3 of 11 steps backwards) ...
    c, sn = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    along = [0, 2, 4, 6, 8, 6, 4, 2, 4, 6, 8, 10]

    def drive(yaw: str) -> str:
        return "t_s,x,y,yaw\n" + "".join(f"{0.25 * i},{a * c:.4f},{a * sn:.4f},{yaw}\n" for i, a in enumerate(along))

    assert len(read_poses(_write(tmp_path, "rev.csv", drive(f"{np.radians(30.0):.6f}")))) == 12
    # ... while degrees are refused despite it (the median ignores the reversing steps)
    with pytest.raises(PoseFileError, match="yaw_deg"):
        read_poses(_write(tmp_path, "revdeg.csv", drive("30.0")))
    # a vehicle standing still: no verdict, read as given
    assert len(read_poses(_write(tmp_path, "still.csv", "t_s,x,y,yaw\n0,0,0,4\n0.25,0,0,4\n0.5,0,0,4\n"))) == 3
    # a drive wholly in reverse (heading pi - 0.05 rad, moving along +x): 180 degrees off as radians, which is a
    # reversing vehicle, not degrees (read as degrees 2.9 degrees would follow the travel: QA re-test, session 23)
    back = "t_s,x,y,yaw\n" + "".join(f"{0.25 * i},{2.0 * i},0,{np.pi - 0.05:.6f}\n" for i in range(12))
    assert read_poses(_write(tmp_path, "allrev.csv", back)).yaw[0] == pytest.approx(np.pi - 0.05, abs=1e-6)


def test_plain_yaw_in_degrees_is_refused_at_any_pose_rate(tmp_path):
    """QA (session 24): a 20 Hz pose file at 8 m/s moves 0.4 m a row, and the guard compared single rows of at least
    0.5 m: degrees in a plain yaw column passed as radians (a map 225 degrees off). Stretches of 0.5 m of path are
    compared now, whatever the rate; GNSS jitter while standing (path without displacement) still gives no verdict."""
    c, s_ = np.cos(np.radians(4.0)), np.sin(np.radians(4.0))
    for hz, speed in ((20, 8.0), (100, 10.0), (200, 2.0)):
        rows = "".join(f"{i / hz:.4f},{speed * i / hz * c:.4f},{speed * i / hz * s_:.4f},4.0\n" for i in range(400))
        with pytest.raises(PoseFileError, match="name the column yaw_deg"):
            read_poses(_write(tmp_path, f"deg{hz}.csv", "t_s,x,y,yaw\n" + rows))
        ok = rows.replace(",4.0\n", f",{np.radians(4.0):.6f}\n")
        assert len(read_poses(_write(tmp_path, f"rad{hz}.csv", "t_s,x,y,yaw\n" + ok))) == 400
    rng = np.random.default_rng(0)
    jitter = rng.normal(scale=0.03, size=(400, 2))  # standing: 400 rows of 3 cm jitter, about 12 m of path
    still = "t_s,x,y,yaw\n" + "".join(f"{i / 100:.2f},{x:.4f},{y:.4f},4.0\n" for i, (x, y) in enumerate(jitter))
    assert len(read_poses(_write(tmp_path, "jitter.csv", still))) == 400


def test_a_time_header_that_contradicts_absolute_values_names_the_column(tmp_path):
    """QA 11: a t_s column holding µs got 'column t: ... give --time-unit us', and that was then refused."""
    text = "t_s,x,y,yaw\n1600000000000000,0,0,0\n1600000000250000,2,0,0\n"
    path = _write(tmp_path, "us.csv", text)
    with pytest.raises(PoseFileError, match=r"column 't_s' declares s, but its values are absolute UTC times in us: "
                                            r"rename the column t_us"):
        read_poses(path)
    with pytest.raises(PoseFileError, match="rename the column t_us"):
        read_poses(path, "us")
    with pytest.raises(PoseFileError, match="rename the column t_us"):
        read_poses(path, "s")
    assert read_poses(_write(tmp_path, "ok.csv", text.replace("t_s", "t_us"))).timestamps_us[1] == 1600000000250000


@pytest.mark.parametrize("head", ["time", "timestamp", "Zeit"])
def test_an_unknown_time_header_lists_the_accepted_names(tmp_path, head):
    """QA 14: 'time,x,y,yaw' gave "timestamp 'time' is not a number"."""
    path = _write(tmp_path, "h.csv", f"{head},x,y,yaw\n0,0,0,0\n0.25,2,0,0\n")
    with pytest.raises(PoseFileError, match=rf"h\.csv:1: the first column is named '{head}'.*t_s, t_ms, t_us or "
                                            r"t_ns.*\(or t for absolute UTC times\).*t_s,x,y,yaw") as err:
        read_poses(path)
    assert "--time-unit" not in str(err.value)  # the same reader serves POST /maps, which has no such option


def test_a_utf8_byte_order_mark_is_no_data(tmp_path):
    """QA 14: a spreadsheet's BOM before t_s gave "timestamp '\\ufefft_s' is not a number"."""
    path = tmp_path / "bom.csv"
    path.write_bytes("\ufefft_s,x,y,yaw\n0,0,0,0\n0.25,2,0,0\n".encode())
    np.testing.assert_array_equal(read_poses(path).timestamps_us, [0, 250_000])
    boreas = tmp_path / "radar_poses.csv"
    boreas.write_bytes(("\ufeff" + ",".join(BOREAS_COLUMNS) + "\n1600000000000000" + ",0" * 12 + "\n").encode())
    assert len(read_poses(boreas)) == 1


def _bend_drive(n: int = 200) -> PoseSequence:
    """A 90-degree left bend of 60 m radius, headings along the road (counter-clockwise from +x)."""
    a = np.linspace(-np.pi / 2, 0.0, n)
    t = 1630597331060160 + np.arange(n, dtype=np.int64) * 50_000
    return PoseSequence(t, 60.0 * np.c_[np.cos(a), np.sin(a)] + [623000.0, 4848000.0], a + np.pi / 2)


def test_headings_of_another_convention_are_refused(tmp_path):
    """QA session 38: a compass heading (clockwise from north) in a Boreas file, and a MulRan rotation written column
    by column, built maps whose keyframes all faced the wrong way, without a word."""
    drive = _bend_drive()
    compass = PoseSequence(drive.timestamps_us, drive.xy, np.pi / 2 - drive.yaw)
    with pytest.raises(PoseFileError, match="heading column does not follow the direction of travel.*compass"):
        read_boreas_radar_poses(write_boreas_radar_poses(compass, tmp_path / "b.csv"))
    transposed = PoseSequence(drive.timestamps_us, drive.xy, -drive.yaw)  # what R.T gives
    with pytest.raises(PoseFileError, match="rotation does not follow the direction of travel.*row by row"):
        read_mulran_global_pose(write_mulran_global_pose(transposed, tmp_path / "m.csv"))
    # the same drive as recorded, and driven with the sensor mounted backwards, read fine
    read_boreas_radar_poses(write_boreas_radar_poses(drive, tmp_path / "ok.csv"))
    backwards = PoseSequence(drive.timestamps_us, drive.xy, drive.yaw + np.pi)
    read_mulran_global_pose(write_mulran_global_pose(backwards, tmp_path / "ok2.csv"))


def _grid_drive() -> PoseSequence:
    """A 200 m square block driven anticlockwise with right-angle corners of 8 m radius, then reversed 20 m along
    its last street (headings counter-clockwise from +x, along the road; the reversing stretch faces forward)."""
    pts, yaws = [], []
    for k in range(4):  # four straights of 184 m, each followed by a quarter turn
        h = k * np.pi / 2
        start = np.array([0.0, 0.0]) if k == 0 else pts[-1]
        d = np.array([np.cos(h), np.sin(h)])
        for s in np.arange(1.0, 185.0, 1.0):
            pts.append(start + s * d)
            yaws.append(h)
        centre = pts[-1] + 8.0 * np.array([-np.sin(h), np.cos(h)])
        for a in np.linspace(0.0, np.pi / 2, 14)[1:]:
            pts.append(centre + 8.0 * np.array([np.sin(h + a), -np.cos(h + a)]))
            yaws.append(h + a)
    back = pts[-1]
    for s in np.arange(1.0, 21.0, 1.0):  # reversing: travel opposite to the heading
        pts.append(back - s * np.array([np.cos(yaws[-1]), np.sin(yaws[-1])]))
        yaws.append(yaws[-1])
    t = 1630597331060160 + np.arange(len(pts), dtype=np.int64) * 100_000
    return PoseSequence(t, np.asarray(pts) + [623000.0, 4848000.0], np.asarray(yaws))


def test_mirrored_headings_on_right_angle_streets_are_refused(tmp_path):
    """QA session 40: on a route of right-angle streets a compass heading or a negated yaw keeps a steady angle to
    the travel modulo 180 degrees, so the steadiness check let both through (every keyframe turned, answers
    90-180 degrees off at confidence 1); the heading turning against the travel at each corner gives them away."""
    drive = _grid_drive()
    compass = PoseSequence(drive.timestamps_us, drive.xy, np.pi / 2 - drive.yaw)
    with pytest.raises(PoseFileError, match="heading column turns against the direction of travel.*compass"):
        read_boreas_radar_poses(write_boreas_radar_poses(compass, tmp_path / "b.csv"))
    transposed = PoseSequence(drive.timestamps_us, drive.xy, -drive.yaw)
    with pytest.raises(PoseFileError, match="rotation turns against the direction of travel.*row by row"):
        read_mulran_global_pose(write_mulran_global_pose(transposed, tmp_path / "m.csv"))
    # as driven (with its reversing stretch), and with the sensor mounted backwards, they read fine
    read_boreas_radar_poses(write_boreas_radar_poses(drive, tmp_path / "ok.csv"))
    backwards = PoseSequence(drive.timestamps_us, drive.xy, drive.yaw + np.pi)
    read_mulran_global_pose(write_mulran_global_pose(backwards, tmp_path / "ok2.csv"))


def test_a_utf16_pose_file_is_told_to_be_saved_as_utf8(tmp_path):
    """QA session 40: Windows PowerShell 5's default output was called binary data."""
    path = tmp_path / "p.csv"
    path.write_bytes("t_s,x,y,yaw\n0,0,0,0\n0.25,2,0,0\n".encode("utf-16"))
    with pytest.raises(PoseFileError, match="UTF-16 text; save the pose file as UTF-8"):
        read_poses(path)


def test_an_empty_pose_file_says_so(tmp_path):
    """QA session 40: an empty pose file was an "unrecognised pose file format"."""
    path = tmp_path / "p.csv"
    path.write_bytes(b"")
    with pytest.raises(PoseFileError, match=r"empty file \(0 bytes\)"):
        read_poses(path)


def test_reader_keeps_only_the_columns_it_needs_and_mixed_integer_times_stay_exact(tmp_path):
    """Rows are parsed as they are read (QA session 40: a 24 MB Boreas file's rows kept as strings took +320 MB):
    the same values as before, integer times exact in int64 until one is not an integer, then every time float."""
    p = tmp_path / "poses.csv"
    p.write_text("t_us,x,y,yaw\n1606417230000001,1.5,2.5,0.1\n1606417230250001,2.5,2.5,0.1\n")
    seq = read_poses(p)
    assert seq.timestamps_us.tolist() == [1606417230000001, 1606417230250001]  # not rounded through float64
    np.testing.assert_allclose(seq.xy, [[1.5, 2.5], [2.5, 2.5]])
    p.write_text("t_s,x,y,yaw\n10,0,0,0\n10.25,1,0,0\n10.5,2,0,0\n")
    seq = read_poses(p)
    assert seq.timestamps_us.tolist() == [10_000_000, 10_250_000, 10_500_000]


def test_a_time_beyond_int64_or_a_header_column_past_the_row_is_a_pose_file_error(tmp_path):
    """Both were other errors before: an OverflowError (a 5xx through the service's upload), and 'non-numeric
    value' for a row that is merely shorter than the header's column order needs."""
    p = tmp_path / "poses.csv"
    p.write_text("t_us,x,y,yaw\n1606417230000000,0,0,0\n99999999999999999999999,1,0,0\n")
    with pytest.raises(PoseFileError, match=r"poses.csv:3: timestamp 99999999999999999999999 is beyond a 64-bit "
                                            r"integer \(after the year 2262 even in nanoseconds\): a corrupt row\?$"):
        read_poses(p)
    # MulRan's ns times too: read as floats after such a row, every other time came out up to 1 us off (QA s41)
    m = tmp_path / "global_pose.csv"
    rows = [f"{1_566_535_940_000_000_123 + 250_000_001 * i},1,0,0,{i},0,1,0,0,0,0,1,0" for i in range(6)]
    m.write_text("\n".join(rows[:3] + ["99999999999999999999," + rows[3].split(",", 1)[1]] + rows[4:]) + "\n")
    with pytest.raises(PoseFileError, match=r"global_pose.csv:4: timestamp 99999999999999999999 is beyond"):
        read_poses(m)
    p.write_text("t_us,x,y,yaw\n-99999999999999999999999,0,0,0\n")
    with pytest.raises(PoseFileError, match=r"poses.csv:2: .* \(before the year 1678 even in nanoseconds\)"):
        read_poses(p)
    m.write_text("\n".join(rows) + "\n")
    assert read_poses(m).timestamps_us.tolist() == [(1_566_535_940_000_000_123 + 250_000_001 * i) // 1000
                                                    for i in range(6)]
    b = tmp_path / "radar_poses.csv"
    b.write_text("GPSTime,easting,northing,altitude,vel_east,vel_north,vel_up,roll,pitch,angvel_z,angvel_y,angvel_x,"
                 "heading\n1606417230000000,0,0,0,0,0,0,0,0,0\n")
    with pytest.raises(PoseFileError, match=r"radar_poses.csv:2: expected at least 13 columns"):
        read_poses(b)


def test_a_line_beyond_the_csv_field_limit_is_a_pose_file_error(tmp_path):
    """QA session 41: one 50 MB line (any pose format) was a csv.Error, a 500 through POST /maps."""
    p = tmp_path / "poses.csv"
    p.write_text("t_us,x,y,yaw\n1606417230000000,0,0,0\n" + "1" * 200_000 + "\n")
    with pytest.raises(PoseFileError, match=r"poses.csv:3: not a pose file row \(field larger than field limit"):
        read_poses(p)
    p.write_text("t_s,x,y," + "a" * 200_000 + "\n1,0,0,0\n")  # the header line too (review: a 500)
    with pytest.raises(PoseFileError, match=r"poses.csv:1: not a pose file row \(field larger than field limit"):
        read_poses(p)
